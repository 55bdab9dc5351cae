"""bonecad: CT scans and meshes of long bones to native CAD models."""
__version__ = "0.1.0"
