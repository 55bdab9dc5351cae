"""Stage 3: the contour curves of the three regions (half-plane and level sections, refitted as cubic B-splines)."""
