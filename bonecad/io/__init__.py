"""Readers and writers: meshes, CT volumes, STEP/IGES, staged output folders."""
