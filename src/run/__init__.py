"""The run plumbing of the entry points: the Trainer of a config, callbacks, logging, run outputs, failures, signals, checkpoints and the command line."""
