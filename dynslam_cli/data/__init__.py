"""Data layer: frames, sequence readers (TUM, Bonn, synthetic), name resolution, download."""
