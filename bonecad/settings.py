"""Typed settings: one frozen dataclass per section of ``data/defaults.toml``.

The figures (angles, control-point counts, tolerances) and the reasons for
them live in the data file, not here: these classes give each one a type and
a unit. ``Settings.load`` lays a user's TOML file (same layout) and then the
command line's overrides over the defaults, checks every key and type, and
returns one frozen tree; each stage receives only its own section.
"""
from __future__ import annotations

import dataclasses
import sys
import typing
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Literal
from collections.abc import Mapping

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from bonecad.errors import InputError

ApexFill = Literal["ring", "patch"]
Joins = Literal["G1", "C0"]
FaceLayout = Literal["tube", "blocks", "elements", "panels"]
ModelName = Literal["nurbs", "tspline"]
BoneChoice = Literal["auto", "tibia", "femur"]
BONES = ("tibia", "femur")
Alignment = Literal["none", "rigid", "similarity"]


@dataclass(frozen=True)
class UnitsSettings:
    """Plausible lengths (mm, long axis) of a tibia and a femur: the tibia's tells the units; beyond both
    one body is two bones fused; they are sanity checks, not a bone's identity (the femur's head is)."""

    tibia_length_mm: tuple[float, float]
    femur_length_mm: tuple[float, float]


@dataclass(frozen=True)
class MeshSettings:
    """Mesh intake: hole filling (edges); the bodies by anatomy: volume shares (of the tibia's volume),
    slenderness (length / width), distances (mm), a share of the tibia's length; fused-bone detection;
    the working copy of a dense mesh (mean edge mm, density factor, largest distance mm)."""

    fragment_volume_share: float
    broken_piece_volume_share: float
    max_hole_edges: int
    long_body_slenderness: float
    thin_body_slenderness: float
    end_zone_share: float
    patella_min_offset_mm: float
    fused_second_loop_mm2: float
    fused_loop_stretch_share: float
    fused_neck_zone_share: float
    fused_neck_ratio: float
    working_edge_mm: float
    working_density_factor: float
    working_max_deviation_mm: float
    working_pass_reduction: float


@dataclass(frozen=True)
class ImagingSettings:
    """CT segmentation: the automatic surface level (cortical floor HU, its percentile, the soft-tissue window
    HU, the level's clamp HU), the bodies of the threshold mask (fragment share of the largest body's voxels,
    long share of the longest length, side-by-side overlap and distance shares), the split of touching bones
    (erosion depth mm, part shares of voxels and length; a bone fused across a broad contact: its marrow cavity's
    least volume, cm^3), the thin-cortex growth (voxels), Taubin smoothing
    (iterations), the spline degree thick slices are interpolated with, and the working voxel (mm) finer scans
    are averaged up to."""

    working_voxel_mm: float
    cortical_min_hu: float
    cortical_percentile: float
    soft_tissue_hu: tuple[float, float]
    level_range_hu: tuple[float, float]
    fragment_voxel_share: float
    long_length_share: float
    beside_overlap_share: float
    beside_distance_share: float
    split_erode_mm: float
    split_part_share: float
    split_length_share: float
    grow_voxels: int
    joint_reach_mm: float
    joint_space_mm: float
    joint_gain_hu_per_mm: float
    smoothing_iterations: int
    slice_spline_degree: int
    split_marrow_cm3: float

    def __post_init__(self) -> None:
        if not 1 <= self.slice_spline_degree <= 5:
            raise ValueError(f"slice_spline_degree {self.slice_spline_degree} must be 1 (no interpolation) to 5")


@dataclass(frozen=True)
class AnatomySettings:
    """Anatomical frame: articular-surface search (shares of the length), metaphysis flare ratios
    (section area / narrowest shaft area), and region boundaries (mm above the plafond centre;
    0: found from the flare)."""

    plateau_search_share: float
    plafond_search_share: float
    distal_flare_ratio: float
    proximal_flare_ratio: float
    distal_boundary_mm: float
    proximal_boundary_mm: float


@dataclass(frozen=True)
class MorphometrySettings:
    """``bonecad measure``: the plateau section (mm below the plateau centre), the condyle centre lines (share
    of the plateau width from each edge), the plateau surface's window for the slopes (mm below the plateau
    centre), the distal articular surface (band about the plafond level, mm; facing within degrees of distal),
    the distal zone of the bimalleolar width (mm above the plafond centre), the medial malleolus's section of the
    torsion (mm below it), the tibial tuberosity's search band and its ends (shares of the mechanical length)."""

    plateau_section_depth_mm: float
    condyle_share: float
    slope_window_mm: float
    plafond_band_mm: float
    plafond_facing_deg: float
    distal_zone_mm: float
    malleolus_depth_mm: float
    tuberosity_band: tuple[float, float]
    tuberosity_band_end: float


@dataclass(frozen=True)
class FemurSettings:
    """The femur's frame: its length (mm); the head's search (share of the length from the narrow end),
    radius range, Hough bin, inlier band (mm), least sphere coverage and least offset from the long axis
    (mm); the knee centre's search (share of the length); the condyles' search height (mm); flare ratios
    and region boundaries as [anatomy]'s; the epicondyles' search radius about the condylar axis and the
    cap of their tops (mm)."""

    head_search_share: float
    head_radius_mm: tuple[float, float]
    head_vote_bin_mm: float
    head_inlier_mm: float
    head_min_coverage: float
    head_min_offset_mm: float
    knee_search_share: float
    condyle_search_mm: float
    distal_flare_ratio: float
    proximal_flare_ratio: float
    distal_boundary_mm: float
    proximal_boundary_mm: float
    epicondyle_reach_mm: float
    epicondyle_cap_mm: float


@dataclass(frozen=True)
class CurvesSettings:
    """Contour curves: half-plane angles (degrees from lateral towards anterior), control points,
    tolerances (mm), shaft section spacing (mm), apex hole radius (mm), the stiffer refit of a curve that
    overshoots (mm; fairness weight)."""

    distal_angles_deg: tuple[float, ...]
    proximal_angles_deg: tuple[float, ...]
    degree: int
    distal_control_points: int
    proximal_control_points: int
    shaft_control_points: int
    distal_tolerance_mm: float
    proximal_tolerance_mm: float
    shaft_tolerance_mm: float
    shaft_sections: int
    shaft_min_spacing_mm: float
    apex_hole_radius_mm: float
    stiff_refit_above_mm: float
    stiff_refit_fairness: float


@dataclass(frozen=True)
class NurbsSettings:
    """NURBS baseline: how the apex holes are filled, how the segments join (G1 or C0), sewing tolerance (mm)."""

    apex_fill: ApexFill
    joins: Joins
    sewing_tolerance_mm: float


@dataclass(frozen=True)
class TSplineSettings:
    """T-spline model: fit tolerances (share within mm, max and RMS mm), fairness weights, budget,
    fit point spacing (mm), starting T-mesh, refinement and noise-aware stopping."""

    target_share_within_mm: tuple[float, float]
    segmented_share_within_mm: tuple[float, float]
    max_deviation_mm: float
    rms_mm: float
    fairness_weight: float
    fit_fairness_weight: float
    max_control_points: int
    fit_point_spacing_mm: float
    fit_copy_edge_mm: float
    initial_s_intervals: int
    initial_t_spacing_mm: float
    apex_rows: int
    max_rounds: int
    min_element_mm: float
    mark_fraction: float
    mark_deficit_factor: float
    split_anisotropy: float
    noise_neighbours: int
    noise_factor: float
    noise_level_radius_mm: float
    noise_level_quantile: float
    noise_level_stride: int
    rough_noise_level_mm: float
    rough_mark_factor: float
    compare_tensor_product: bool
    face_layout: FaceLayout
    panel_face_cost: float
    panel_t_step: int


@dataclass(frozen=True)
class TemplateSettings:
    """The template T-mesh (one topology for every tibia): its parameter domain (template mm), knot
    intervals per region, the share of the proximal meridians where the tuberosity's height lands, T-junction
    layout, fit controls (fairness weights, parameter corrections,
    point spacing mm) and the figures it reports (share within mm, max and RMS mm)."""

    s_period_mm: float
    distal_length_mm: float
    shaft_length_mm: float
    proximal_length_mm: float
    s_intervals: int
    shaft_s_intervals: int
    distal_t_intervals: int
    shaft_t_intervals: int
    proximal_t_intervals: int
    tuberosity_share: float
    apex_rows: int
    shaft_transition_rows: int
    fairness_weight: float
    fit_fairness_weight: float
    corrections: int
    fit_point_spacing_mm: float
    target_share_within_mm: tuple[float, float]
    max_deviation_mm: float
    rms_mm: float


@dataclass(frozen=True)
class ShapeModelSettings:
    """The statistical shape model: Procrustes alignment ("none", "rigid", "similarity"), the ridge
    weight of the parameter regression, the margin outside the training range a morph accepts (share
    of the range), random samples for the specificity, their seed, surface samples per distance."""

    alignment: Alignment
    ridge: float
    range_margin: float
    specificity_samples: int
    seed: int
    surface_samples: int


@dataclass(frozen=True)
class AnalysisSettings:
    """Deviation histogram bands (mm), samples per direction, tessellation (mm, rad, relative),
    seam classes (gap mm, angle degrees, relative curvature jump, flat radius mm), triangles per mesh
    in the report's 3-D view, height of the figures' images (px)."""

    band_width_mm: float
    band_limit_mm: float
    sample_points: int
    tessellation_deflection_mm: float
    tessellation_angular_deflection_rad: float
    tessellation_max_edge_mm: float
    coverage_tolerance: float
    small_face_shortfall_factor: float
    area_rel_eps: float
    continuity_gap_mm: float
    continuity_angle_deg: float
    continuity_curvature_jump: float
    continuity_curvature_radius_ref_mm: float
    view_max_triangles: int
    figure_height_px: int
    fairness_step_mm: float

    def __post_init__(self) -> None:
        width, limit = self.band_width_mm, self.band_limit_mm
        if width <= 0 or limit <= 0 or abs(round(2 * limit / width) * width - 2 * limit) > 1e-9 * limit:
            raise ValueError(f"band_limit_mm {limit} must be a whole number of band_width_mm {width} (both > 0)")


@dataclass(frozen=True)
class PatchSettings:
    """``bonecad patch``: named regions (height from, to in mm above the frame's origin; angle from, to in
    degrees from lateral towards anterior), the patch's samples for its deviation from the mesh (per
    direction), and the plate blank it must thicken into (mm)."""

    anteromedial_distal_tibia: tuple[float, float, float, float]
    anterolateral_distal_tibia: tuple[float, float, float, float]
    lateral_distal_femur: tuple[float, float, float, float]
    mesh_samples: int
    plate_thickness_mm: float


@dataclass(frozen=True)
class PlateSettings:
    """``bonecad plate``: the plate's width (distal, proximal end), the bone's face it may cover (degrees
    round the bone about the region's middle angle), thickness, gap to the bone, end corner
    radius, end inset and the knot spacings of a smoothed underside tried in turn where the exact one gives no
    valid solid (mm); its holes (count, 0 = by spacing; spacing, end distance, diameter, mm); the
    screws (diameter, per-hole tilts [along, across] in degrees, maximum and stock step of their length,
    mm); the joint margin (mm), the fit's sample spacing (mm), the material's density (g/cm^3), and on a
    reduced fracture the screws each main fragment needs and how far (mm) screws keep from a fracture line."""

    width_mm: tuple[float, float]
    face_angle_deg: float
    thickness_mm: float
    gap_mm: float
    end_radius_mm: float
    end_inset_mm: float
    underside_smoothing_mm: tuple[float, ...]
    holes: int
    hole_spacing_mm: float
    hole_end_distance_mm: float
    hole_diameter_mm: float
    screw_diameter_mm: float
    screw_direction: Literal["normal", "transverse"]
    screw_angles_deg: tuple[tuple[float, float], ...]
    max_screw_length_mm: float
    stock_step_mm: float
    joint_margin_mm: float
    fit_sample_mm: float
    density_g_cm3: float
    screws_per_fragment: int
    fracture_margin_mm: float

    def __post_init__(self) -> None:
        positive = {"width_mm": min(self.width_mm), "thickness_mm": self.thickness_mm,
                    "end_radius_mm": self.end_radius_mm, "hole_spacing_mm": self.hole_spacing_mm,
                    "hole_diameter_mm": self.hole_diameter_mm, "screw_diameter_mm": self.screw_diameter_mm,
                    "max_screw_length_mm": self.max_screw_length_mm, "stock_step_mm": self.stock_step_mm,
                    "fit_sample_mm": self.fit_sample_mm, "density_g_cm3": self.density_g_cm3,
                    "underside_smoothing_mm": min(self.underside_smoothing_mm, default=1.0)}
        bad = [k for k, v in positive.items() if not v > 0]
        if bad:
            raise ValueError(f"{bad} must be > 0")
        if not 0 < self.face_angle_deg < 360:
            raise ValueError(f"face_angle_deg {self.face_angle_deg} must lie between 0 and 360")
        if self.gap_mm < 0 or self.holes < 0 or self.end_inset_mm < 0 or self.joint_margin_mm < 0:
            raise ValueError("gap_mm, holes, end_inset_mm and joint_margin_mm must be >= 0")
        if 2 * self.end_radius_mm > min(self.width_mm) + 1e-9:
            raise ValueError(f"end_radius_mm {self.end_radius_mm} is more than half the width {min(self.width_mm)}")
        if self.hole_diameter_mm >= min(self.width_mm):
            raise ValueError(f"hole_diameter_mm {self.hole_diameter_mm} leaves no plate either side "
                             f"(width {min(self.width_mm)} mm)")
        if self.screw_diameter_mm > self.hole_diameter_mm:
            raise ValueError(f"screw_diameter_mm {self.screw_diameter_mm} does not pass the "
                             f"{self.hole_diameter_mm} mm hole")


@dataclass(frozen=True)
class PipelineSettings:
    """The runner: which models to build, whether independent stages run on the second core, which bone
    (a profile of data/bones, or "auto": recognised), whether a reconstruction's arrays may live on
    transparent huge pages (``run.executor.huge_pages``)."""

    models: tuple[ModelName, ...]
    background_jobs: bool
    bone: BoneChoice
    huge_pages: bool


@dataclass(frozen=True)
class CohortSettings:
    """``bonecad cohort``: local worker processes (0: one per CPU core), Dask task retries, worker deaths a bone
    may cause before it is marked failed, and the time (s) after which a running bone is marked failed."""

    workers: int
    retries: int
    allowed_failures: int
    timeout_s: float

    def __post_init__(self) -> None:
        if self.workers < 0 or self.retries < 0 or self.allowed_failures < 0 or self.timeout_s <= 0:
            raise ValueError("workers, retries and allowed_failures must be >= 0 and timeout_s > 0")


@dataclass(frozen=True)
class FractureSettings:
    """Fracture reduction (``analysis.reduction``): sample spacings (mm) of the template and the fragments, the
    starts (turns about the axis, the band of an end as a share of the length, an intermediate fragment's search
    along the axis mm), the ICP (iterations per start and in all, trim floor mm, cosine of the largest normal
    disagreement), fracture faces (distance mm), the joint refinement (rounds, contact reach mm, contact's
    share of the weight), a poor registration (RMS mm, share of points kept), specks (share of the fragments'
    volume), and the templates' expected uncertainties (mm, degrees)."""

    template_spacing_mm: float
    fragment_spacing_mm: float
    fragment_points: int
    start_points: int
    start_turns: int
    end_band_share: float
    intermediate_search_mm: float
    start_iterations: int
    icp_iterations: int
    trim_floor_mm: float
    normal_cos: float
    fracture_distance_mm: float
    joint_rounds: int
    contact_mm: float
    contact_share: float
    intermediate_contact_share: float
    poor_rms_mm: float
    poor_inlier_share: float
    speck_volume_share: float
    same_side_rms_ratio: float
    contralateral_uncertainty_mm: float
    contralateral_uncertainty_deg: float
    exclusion_mm: float


@dataclass(frozen=True)
class FESettings:
    """``bonecad fe``: tetrahedra (largest edge mm, order, Netgen's optimiser on, elements per turn of
    curvature, smallest edge as a share of the largest, most elements), the end node sets' depth (mm),
    the solver check; HU -> density calibration ([slope g/cm3 per HU, intercept g/cm3], or [] for none),
    ash from QCT density ([slope, intercept]), ash over apparent density, E = a rho^b (MPa, [a, b]) of
    the "ash" or "apparent" density, its floor (MPa), the homogeneous cortical modulus (MPa) and
    Poisson's ratio, the largest number of materials, the CT quadrature's sub-tetrahedron length
    (voxels)."""

    size_mm: float
    order: int
    netgen: bool
    curvature_elements: int
    min_size_share: float
    max_elements: int
    end_depth_mm: float
    solver_check: bool
    hu_to_density: tuple[float, ...]
    ash_from_qct: tuple[float, float]
    ash_share_of_apparent: float
    modulus_law: tuple[float, float]
    modulus_density: Literal["ash", "apparent"]
    min_modulus_mpa: float
    cortical_modulus_mpa: float
    poisson: float
    materials: int
    quadrature_voxels: float

    def __post_init__(self) -> None:
        if self.size_mm <= 0 or self.order not in (1, 2) or self.materials < 1 or self.max_elements < 1:
            raise ValueError("size_mm must be > 0, order 1 or 2, materials and max_elements >= 1")
        if len(self.hu_to_density) not in (0, 2):
            raise ValueError("hu_to_density: [slope, intercept] or [] (no calibration)")


@dataclass(frozen=True)
class Settings:
    """Every setting of a run, one section per stage (see ``data/defaults.toml``)."""

    units: UnitsSettings
    mesh: MeshSettings
    imaging: ImagingSettings
    anatomy: AnatomySettings
    morphometry: MorphometrySettings
    femur: FemurSettings
    curves: CurvesSettings
    nurbs: NurbsSettings
    tspline: TSplineSettings
    template: TemplateSettings
    shape_model: ShapeModelSettings
    analysis: AnalysisSettings
    patch: PatchSettings
    plate: PlateSettings
    pipeline: PipelineSettings
    cohort: CohortSettings
    fracture: FractureSettings
    fe: FESettings

    @classmethod
    def load(cls, path: str | Path | None = None,
             overrides: Mapping[str, Mapping[str, Any]] | None = None) -> Settings:
        """The defaults, then the TOML file ``path`` (if given), then ``overrides``
        ({section: {key: value}}, e.g. from command-line flags) laid over them."""
        tree = _read_defaults()
        if path is not None:
            try:
                user = tomllib.loads(Path(path).read_text())
            except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
                raise InputError(f"cannot read configuration: {exc}", path) from exc
            tree = _merged(tree, user, path)
        if overrides:
            tree = _merged(tree, {k: dict(v) for k, v in overrides.items() if v}, path)
        return _build(cls, tree, "", path)

    def for_bone(self, profile: BoneProfile) -> Settings:
        """These settings with the bone profile's own values (its [settings] table) laid over them."""
        if not profile.settings:
            return self
        return Settings.load(overrides=_merged(self.to_dict(), profile.settings, profile.name))

    def replace(self, section: str, **values: Any) -> Settings:
        """A copy with some values of one section changed (checked like a file's)."""
        return Settings.load(overrides={**self.to_dict(), section: values}) if values else self

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """The settings as the TOML layout (tuples as lists)."""
        return {name: {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(section).items()}
                for name, section in ((f.name, getattr(self, f.name)) for f in dataclasses.fields(self))}


@dataclass(frozen=True)
class BoneProfile:
    """What differs per bone (``data/bones/<name>.toml``): how to recognise it and its ends, the frame
    strategy and its centreline, the side rule, the frame's origin (heights are mm above it), the regions'
    names, the named patch regions on it, and settings of its own. body: the
    body the intake keeps from a mesh of several bones (``mesh.intake.prepare_bone``'s ``keep``)."""

    name: str
    description: str
    wider_end: Literal["proximal", "distal"]
    narrow_end: str
    body: Literal["tibia", "femur"]
    frame: Literal["tibia", "femur"]
    centreline: Literal["straight", "curved"]
    side_rule: str
    origin: str
    regions: Mapping[str, str]
    patch_regions: tuple[str, ...]
    settings: Mapping[str, Any]


def load_profile(name: str) -> BoneProfile:
    """The profile of a bone (one of ``BONES``)."""
    if name not in BONES:
        raise InputError(f"no bone profile {name!r}; the profiles are {list(BONES)}")
    data = tomllib.loads(resources.files("bonecad").joinpath(f"data/bones/{name}.toml").read_text())
    recognise, frame = data["recognise"], data["frame"]
    return BoneProfile(
        name=data["name"], description=data["description"],
        wider_end=_typed(recognise["wider_end"], Literal["proximal", "distal"], f"{name}.wider_end", None),
        narrow_end=recognise["narrow_end"],
        body=_typed(recognise["body"], Literal["tibia", "femur"], f"{name}.body", None),
        frame=_typed(frame["strategy"], Literal["tibia", "femur"], f"{name}.strategy", None),
        centreline=_typed(frame["centreline"], Literal["straight", "curved"], f"{name}.centreline", None),
        side_rule=frame["side_rule"], origin=frame["origin"], regions=dict(data["regions"]),
        patch_regions=tuple(data["patch"]["regions"]), settings=dict(data.get("settings", {})))


def _read_defaults() -> dict[str, Any]:
    text = resources.files("bonecad").joinpath("data/defaults.toml").read_text()
    return tomllib.loads(text)


def _merged(base: dict[str, Any], override: Mapping[str, Any], path: str | Path | None,
            where: str = "") -> dict[str, Any]:
    """``base`` with ``override`` laid over it; unknown keys and tables given as values are errors."""
    out = dict(base)
    for key, value in override.items():
        if key not in base:
            raise InputError(f"unknown setting '{where}{key}'", path)
        if isinstance(base[key], dict):
            if not isinstance(value, Mapping):
                raise InputError(f"setting '{where}{key}' must be a table", path)
            out[key] = _merged(base[key], value, path, f"{where}{key}.")
        else:
            out[key] = value
    return out


def _build(cls: type, table: Mapping[str, Any], where: str, path: str | Path | None) -> Any:
    hints = typing.get_type_hints(cls)
    missing = [f.name for f in dataclasses.fields(cls) if f.name not in table]
    if missing:
        raise InputError(f"settings '{where}' lack {missing} (data/defaults.toml is incomplete)", path)
    values = {}
    for f in dataclasses.fields(cls):
        name = f"{where}{f.name}"
        values[f.name] = (_build(hints[f.name], table[f.name], f"{name}.", path)
                          if dataclasses.is_dataclass(hints[f.name])
                          else _typed(table[f.name], hints[f.name], name, path))
    try:
        return cls(**values)
    except ValueError as exc:  # a section's own consistency check
        raise InputError(f"settings '{where.rstrip('.')}': {exc}", path) from None


def _typed(value: Any, hint: Any, name: str, path: str | Path | None) -> Any:
    """``value`` checked against ``hint`` (float, int, bool, str, Literal, tuple[...]), ints widened to float."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is Literal:
        if value not in args:
            raise InputError(f"setting '{name}' must be one of {list(args)}, got {value!r}", path)
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise InputError(f"setting '{name}' must be a list, got {value!r}", path)
        items = args[:1] * len(value) if len(args) == 2 and args[1] is Ellipsis else args
        if len(items) != len(value):
            raise InputError(f"setting '{name}' must have {len(items)} values, got {len(value)}", path)
        return tuple(_typed(v, h, name, path) for v, h in zip(value, items))
    if hint is bool:
        if not isinstance(value, bool):
            raise InputError(f"setting '{name}' must be true or false, got {value!r}", path)
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(f"setting '{name}' must be an integer, got {value!r}", path)
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(f"setting '{name}' must be a number, got {value!r}", path)
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise InputError(f"setting '{name}' must be a string, got {value!r}", path)
        return value
    raise TypeError(f"setting '{name}': unsupported type {hint!r}")
