"""Timing: inference per method (:mod:`.inference`, ``python -m benchmarks.speed``), a network's training step
(:mod:`.train_step`), the training pairs a loader makes per CPU-second (:mod:`.loader`), a time-boxed trial of the
paper's training on a GPU (:mod:`.gpu_trial`)."""
