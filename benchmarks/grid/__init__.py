"""The comparison grid: plan the cells (:mod:`.plan`), run and score them (:mod:`.run`), report (:mod:`.report`); ``python -m benchmarks.grid`` (:mod:`.cli`)."""
