"""Vectorised geometry: boxes, cropping, the canonical car frame, partitions."""
