"""End-to-end pipelines, the only package that imports every stage: the demo (batch) and the online (frame-by-frame) mode."""
