"""Mesh intake: reading, cleanup, bodies, units, the tibia's own body."""
