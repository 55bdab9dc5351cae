"""The OpenCascade bridge, the only package that imports OCP: numpy splines <-> Geom
curves and surfaces, B-rep building, sewing and checks, tessellation, seam sampling,
STEP/IGES reading and writing."""
