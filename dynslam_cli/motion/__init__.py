"""Learning to forget: instance segmentation, embeddings, the continual motion classifier."""
