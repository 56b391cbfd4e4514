"""Geometry: SE(3)/so(3) Lie algebra (``lie``), pinhole camera rays and projection (``camera``),
Umeyama alignment (``align``)."""
