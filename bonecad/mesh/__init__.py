"""Triangle meshes: the bone mesh and its intake (reading, cleanup, bodies, units), sampling, closest
points, planar sections, and the tessellation of spline surfaces."""
