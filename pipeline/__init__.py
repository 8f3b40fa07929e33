"""End-to-end pipelines over the stages: the online (frame-by-frame) mode."""
