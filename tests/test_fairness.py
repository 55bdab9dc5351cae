"""The fairness figure (bonecad.analysis.fairness, issue 47): it ranks surfaces as their zebra stripes do.

A smooth bicubic surface (a bent sheet, 40 x 40 mm) gets ripples of 0.02-0.1 mm at 2-5 mm wavelength: the
figure grows with every step of the ripple, while the share of the rippled surface within 0.25 mm of the
smooth one does not move (every ripple is under the deviation bars)."""
from __future__ import annotations

import numpy as np
import pytest

from bonecad.analysis.fairness import surface_fairness
from bonecad.splines.surface import BSplineSurface

SIZE_MM, POLE_STEP_MM = 40.0, 0.25


def _smooth(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A gently bent sheet (curvature radii 25-60 mm, like a tibia's shaft), mm."""
    return x**2 / 50.0 + y**2 / 120.0 + 0.4 * np.sin(x / 9.0) * np.cos(y / 13.0)


def _sheet(amplitude_mm: float = 0.0, wavelength_mm: float = 3.0, *, flat: bool = False) -> BSplineSurface:
    """A height-field B-spline whose poles sample the sheet plus a ripple a sin(2 pi x / L) sin(2 pi y / L)
    (poles every 0.25 mm: the cubic spline keeps most of even a 2 mm ripple)."""
    n = int(SIZE_MM / POLE_STEP_MM) + 1
    knots = np.concatenate([[0.0] * 3, np.linspace(0.0, 1.0, n - 2), [1.0] * 3])
    greville = (knots[1:-3] + knots[2:-2] + knots[3:-1]) / 3  # poles there: x(u) linear, uniform speed
    g = SIZE_MM * (greville - 0.5)
    x, y = np.meshgrid(g, g, indexing="ij")
    k = 2 * np.pi / wavelength_mm
    z = (0.0 if flat else _smooth(x, y)) + amplitude_mm * np.sin(k * x) * np.sin(k * y)
    return BSplineSurface(np.stack([x, y, z], axis=2), knots, knots)


def _share_within(surface: BSplineSurface, mm: float) -> float:
    """Share of the surface's points (a parameter grid) within mm of the smooth sheet (vertical distance,
    an upper bound of the normal one)."""
    u = np.linspace(0.0, 1.0, 201)
    p = surface.evaluate(*np.meshgrid(u, u, indexing="ij")).points
    return float(np.mean(np.abs(p[:, 2] - _smooth(p[:, 0], p[:, 1])) <= mm))


@pytest.mark.parametrize("wavelength_mm", [2.0, 3.5, 5.0])
def test_fairness_grows_with_the_ripple_while_the_share_within_tolerance_does_not_move(wavelength_mm):
    amplitudes = [0.0, 0.02, 0.05, 0.1]
    figures, shares = [], []
    for a in amplitudes:
        sheet = _sheet(a, wavelength_mm)
        figures.append(surface_fairness([sheet], step_mm=0.25).curvature_variation)
        shares.append(_share_within(sheet, 0.25))
    assert all(b > 1.5 * a for a, b in zip(figures, figures[1:])), figures  # strictly and clearly growing
    typical = [surface_fairness([_sheet(a, wavelength_mm)], step_mm=0.25).typical for a in amplitudes]
    assert all(b > 1.5 * a for a, b in zip(typical, typical[1:])), typical  # the median too: the ripple is everywhere
    assert max(shares) - min(shares) <= 0.001 and min(shares) >= 0.999, shares


def test_shorter_ripple_is_less_fair_at_the_same_amplitude():
    figures = [surface_fairness([_sheet(0.05, wl)], step_mm=0.25).curvature_variation for wl in (5.0, 3.5, 2.0)]
    assert figures[0] < figures[1] < figures[2], figures


def test_ripple_figure_matches_its_closed_form():
    """A ripple a sin(kx) sin(ky) on a plane: H ~ -a k^2 sin sin, |grad H|^2 averages a^2 k^6 / 2, so F is
    a k^3 / sqrt(2) (less the cubic spline's and the differences' few per cent at this wavelength)."""
    a, wl = 0.05, 4.0
    k = 2 * np.pi / wl
    figure = surface_fairness([_sheet(a, wl, flat=True)], step_mm=0.2).curvature_variation
    assert figure == pytest.approx(a * k**3 / np.sqrt(2), rel=0.15)


def test_one_sharp_spot_moves_the_energy_not_the_median():
    """A bump of 0.3 mm and 1.5 mm radius on 0.1 % of the sheet: F grows several times, the median does not."""
    smooth, spot = _sheet(), _sheet()
    x, y = spot.poles[..., 0], spot.poles[..., 1]
    poles = spot.poles.copy()
    poles[..., 2] += 0.3 * np.exp(-0.5 * ((x - 5.0) ** 2 + (y + 3.0) ** 2) / 1.5**2)
    spot = BSplineSurface(poles, spot.knots_u, spot.knots_v)
    a, b = (surface_fairness([s], step_mm=0.25) for s in (smooth, spot))
    assert b.curvature_variation > 3 * a.curvature_variation
    assert b.typical == pytest.approx(a.typical, rel=0.1)


def test_smooth_sheet_is_fair_and_regions_split_the_area():
    sheet = _sheet()
    fair = surface_fairness([sheet], step_mm=0.5, labels=lambda p: np.where(p[:, 0] < 0, "left", "right"))
    assert fair.curvature_variation < 0.002  # the sheet's own curvature varies by ~1e-3 /mm per mm
    assert set(fair.regions) == {"left", "right"}
    assert sum(fair.region_area_mm2.values()) == pytest.approx(fair.area_mm2)
    u = np.linspace(0.0, 1.0, 301)
    p = sheet.evaluate(*np.meshgrid(u, u, indexing="ij")).points.reshape(301, 301, 3)
    a, b, c, d = p[:-1, :-1], p[1:, :-1], p[1:, 1:], p[:-1, 1:]
    area = 0.5 * (np.linalg.norm(np.cross(b - a, c - a), axis=-1)
                  + np.linalg.norm(np.cross(c - a, d - a), axis=-1)).sum()
    assert fair.area_mm2 == pytest.approx(area, rel=1e-3)  # the grid's area element integrates the surface
    assert fair.to_dict()["units"] == "1/mm^2"


def test_bad_step_is_refused():
    with pytest.raises(ValueError, match="step_mm"):
        surface_fairness([_sheet()], step_mm=0.0)


def test_report_carries_the_fairness_per_model_and_on_its_card():
    from bonecad.analysis.fairness import Fairness
    from bonecad.analysis.model import ModelReport
    from bonecad.export.report import build_report
    from bonecad.export.report_page import _model_card

    fair = Fairness(0.0768, {"distal": 0.12, "shaft": 0.03, "proximal": 0.15}, 45000.0,
                    {"distal": 9000.0, "shaft": 20000.0, "proximal": 16000.0}, 0.5, 15)
    report = build_report(input_summary={}, frame={}, timings_s={},
                          models=[ModelReport("tspline", fairness=fair), ModelReport("nurbs")])
    assert report["models"]["tspline"]["fairness"]["curvature_variation_per_mm2"] == 0.0768
    assert report["models"]["tspline"]["fairness"]["units"] == "1/mm^2"
    assert report["models"]["nurbs"]["fairness"] is None
    card = report["summary"]["tspline"]
    assert card["fairness"] == {"curvature_variation_per_mm2": 0.0768, "typical_per_mm2": 0.0,
                                "regions": {"distal": 0.12, "shaft": 0.03, "proximal": 0.15}}
    assert report["summary"]["nurbs"]["fairness"] is None
    page = _model_card("tspline", card)
    assert "fairness: curvature variation" in page and "0.0768" in page
