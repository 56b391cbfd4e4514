"""Synthetic dynamic RGB-D scenes with per-pixel ground truth (motion masks, instance ids, static mesh).

Modules (none is imported here: ``config`` imports this package, keep it light):

- ``render``: ``render_preset(preset, out_dir, cfg, frames, progress) -> SynthResult``, ``PRESETS``;
  writes the scene folder described in DEVELOPING.md.
- ``scene``: room, furniture, articulated walkers, ball, hand-held / following cameras, presets.
- ``raycast``: the numba ray caster (boxes and ellipsoids, per-tile culling, textures, shading).
- ``sensor``: depth noise ~ z^2, random and edge holes, quantisation; colour noise.
- ``textures``: procedural textures (value noise, tiles, planks, posters, fabric, ...).
- ``geometry``: rotations, primitives (``Parts``), floor paths.
"""
