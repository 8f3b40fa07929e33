"""The end-to-end pipeline: the only package that imports every stage."""
