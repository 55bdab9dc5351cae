"""Benchmark of the T-spline core: prints its figures (seconds) and the targets.

- evaluation of 1 M points on a locally refined tube (target < 1 s);
- Bezier extraction of a T-mesh with about 10 k elements (target < 2 s);
- conversion of about 5 k Bezier elements to faces and sewing (target < 10 s).

Run: python benchmarks/bench_tspline.py
"""
from __future__ import annotations

import time

import numpy as np

from bonecad.splines.tspline import TMesh, TSpline, check_suitability, extract, refine_elements


def tube(n_s: int, n_t: int, *, radius_mm: float = 20.0, length_mm: float = 300.0) -> TSpline:
    """A tensor-product tube with n_s x (n_t - 1) elements, s periodic (period n_s)."""
    theta = 2 * np.pi * np.arange(n_s) / n_s
    z = np.linspace(0.0, length_mm, n_t + 2)
    r = radius_mm * (1.0 + 0.1 * np.sin(3 * theta))[:, None] * (1.0 + 0.2 * np.cos(z / 40.0))[None, :]
    cp = np.stack([r * np.cos(theta)[:, None], r * np.sin(theta)[:, None], np.broadcast_to(z, r.shape)], axis=-1)
    return TSpline.from_grid(np.arange(n_s, dtype=float), np.linspace(0.0, 1.0, n_t), cp, s_period=float(n_s))


def timed(label: str, target: float, fn, *, repeat: int = 3):
    """Run fn ``repeat`` times (the first also warms caches); print the best time."""
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    print(f"{label:<52s} {best:7.3f} s   (target < {target:g} s, best of {repeat})")
    return out


def main() -> None:
    rng = np.random.default_rng(0)
    base = tube(48, 40)
    ts = refine_elements(base, rng.choice(base.extraction.n_elements, 60, replace=False)).tspline
    print(f"refined tube: {ts.n_control} control points, {ts.extraction.n_elements} elements, "
          f"analysis-suitable: {check_suitability(ts.mesh).suitable}")
    n = 1_000_000
    s = rng.uniform(0.0, 48.0, n)
    t = rng.uniform(0.0, 1.0, n)
    timed("evaluate 1 M points (positions)", 1.0, lambda: ts.evaluate(s, t))
    timed("evaluate 1 M points (with 1st and 2nd derivatives)", 3.0, lambda: ts.evaluate(s, t, order=2))
    timed("basis matrix, 100 k points", 1.0, lambda: ts.basis_matrix(s[:100_000], t[:100_000]))

    big = tube(100, 101)
    big = refine_elements(big, rng.choice(big.extraction.n_elements, 100, replace=False)).tspline
    mesh = big.mesh

    def fresh_extraction():
        """Extraction from a new mesh object (no cached ray casting)."""
        return extract(TMesh(mesh.s_lines, mesh.t_lines, mesh.s_edges, mesh.t_edges, mesh.s_period))

    ext = timed("Bezier extraction incl. ray casting (~10 k elements)", 2.0, fresh_extraction)
    print(f"    {ext.n_elements} elements, {len(ext.pair_anchor)} element-function pairs")

    from bonecad.occ.brep import is_valid, sew
    from bonecad.occ import tspline as occ

    mid = tube(64, 80)
    mid = refine_elements(mid, rng.choice(mid.extraction.n_elements, 40, replace=False)).tspline
    print(f"sewing test: {mid.extraction.n_elements} elements")
    faces = timed("Bezier faces", 10.0, lambda: occ.bezier_faces(mid), repeat=1)
    shell = timed("sewing into one shell", 10.0, lambda: sew(faces, tolerance_mm=1e-6, closed=False)[0], repeat=1)
    print(f"    valid shell: {is_valid(shell)}")


if __name__ == "__main__":
    main()
