"""Neural map: hash grid + one-blob encoding, SDF/colour decoders, TSDF volume rendering."""
