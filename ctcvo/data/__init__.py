"""Data layer: dataset readers (7-Scenes, TUM RGB-D, synthetic), geometry conventions,
file formats and evaluation metrics shared by every stage."""
