"""Plots: a sweep's metric against its swept value (:mod:`.sweep`, ``python -m benchmarks.plots``) and figures of registered pairs (:mod:`.figures`)."""
