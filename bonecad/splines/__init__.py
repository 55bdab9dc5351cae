"""The spline kernel: B-spline curves and surfaces, their evaluation, projection and
least-squares fitting, and the T-spline library. numpy/scipy only: it knows neither
bones nor OpenCascade."""
