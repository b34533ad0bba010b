"""Stage A — ``lithos-select``: which maplets a photo can see.

Implements L15 §3.2 ("Determining Which Maplets are Visible in a Photo") and §3.2.1 ("Checking For
Hidden Maplets") as corrected and specified in ``spc-algorithms.md`` §2 (Stage A), §11 (errata 6–11,
33) and §13 (defaults); pixel conventions from ``spc-formats.md`` §2.5 (in-image test
1 ≤ sample ≤ NPX, 1 ≤ line ≤ NLN) and maplet axes from §1.2 (UY East, UX South).  Every candidate
is tested with array operations — there is no per-landmark Python loop, and the occlusion test is
one batched ray query.

Checks, in L15's order; a candidate's ``status`` is the first check it fails (``ok`` if none):

1. ``outside`` — angular cone (L15 Eq. 3.1–3.11).  Λ_c is the largest angle between the boresight
   b̂ and the line of sight through any point of the photo boundary (sampled along the four edges,
   so distortion and the K x·y terms are honoured); b̂ is the line of sight through the photo's
   centre point ((NPX+1)/2, (NLN+1)/2), not the principal point (erratum 6).  The maplet's angular
   half-size Λ_m is that of a sphere of radius ρ around the landmark, sin Λ_m = ρ/d, with
   ρ = d_m/√2 (``cone_rho="half-diagonal"``, default) or d_m/2 (``"half-side"``), and ρ never
   smaller than the radius of the fine-test box below.  This departs from L15 Eq. 3.8: erratum 7
   fixes its units (√(d² + ρ²) instead of √(d² + d_m/2)), and the tangent-sphere form
   (cos Λ_m = √(d² − ρ²)/d instead of d/√(d² + ρ²)) also covers a corner tilted toward the
   camera, so the cone can never reject a maplet that the fine test (7) would keep.  Keep if
   b̂·v̂ > cos(Λ_c + Λ_m) (the angle-sum formula, erratum 8).
2. ``backfacing`` — −v̂·Uz > ``facing_cos_min`` (0.05; L15 Eq. 3.12).
3. ``too-oblique`` — only when ``max_emission`` is set: emission < ``max_emission`` (LITHOS limits
   PICTLIST candidates to 75°; spc-algorithms.md §2.2).
4. ``unlit`` — Uz·ŝ > 0 (L15 Eq. 3.13); ŝ is the body→Sun unit vector (SUM SZ).
5. ``too-coarse`` — resolution.  J_xy = ∂(sample, line)/∂(x, y) by central differences with a step
   of one maplet cell along Ux (x) and Uy (y) (L15 Eq. 3.15; ``jacobian="analytic"`` uses the
   camera's exact derivative instead); r_img = s_m/√|det J_xy| km per pixel (erratum 9: det J is an
   area ratio).  The test keeps r_img < RESLM·s_m (erratum 10: SPC's INIT_LITHOS comment "PIXEL <
   RESLM·SCALE"; L15's "r_img > r_thresh" has the direction reversed) and is applied under the
   NUMLM rule (L15 footnote 18):

   * ``numlm_mode="deterministic"`` (default): when more than NUMLM candidates pass every *other*
     check, the resolution test is applied to all candidates; with NUMLM or fewer it is not applied;
   * ``numlm_mode="spc_sequential"``: candidates are taken in the given (LMRKLIST) order and the
     test is applied to a candidate once NUMLM maplets have already been selected before it — SPC's
     order-dependent behaviour.  (Vectorised: while fewer than NUMLM are selected every candidate
     that passes the other checks is selected, so candidate i is tested iff at least NUMLM earlier
     candidates pass every other check.)
6. ``too-big`` — d_m < r_img·min(NPX, NLN)·``size_factor`` (L15 Eq. 3.16; INIT_LITHOS SIZLM taken
   as ``size_factor``, which is [UNVERIFIED]).  d_m = (2·QSZ + 1)·s_m.
7. ``outside`` — fine in-photo test: the 3×3 box of points V + fw·w·(k·Ux + j·Uy), j, k ∈ {−1, 0, 1}
   (L15 Eq. 3.17 with erratum 11's missing "+"), w = ``fractional_width`` (0.5) and fw = d_m
   (``fw_scale="side"``, reading (a), default: with w = 0.5 the outer points are the maplet's edge
   midpoints and corners) or d_m/2 (``"half"``, reading (b)).  Kept when any of the 9 points lies in
   front of the camera with 1 ≤ sample ≤ NPX and 1 ≤ line ≤ NLN.  ``fraction_in_photo`` is the
   fraction of these 9 points in the photo.
8. ``occluded`` — L15 §3.2.1 via :func:`spctool.geometry.shape.visible_from`: the first surface hit
   on the line of sight from the camera to V must lie within ``occlusion_tol``·D_max (0.01 of the
   body's largest diameter) of V.  The line of sight is the straight camera→V ray (no iterative
   undistortion; erratum 33, L15 footnote 20).  Only candidates that pass checks 1–4, 6 and 7 are
   traced, in one batched query.  SPC's tutorial answer to "Reject invisibles?" is *no*; spctool
   runs the test by default **whenever a shape is supplied** (``occlusion=None`` = auto) and skips
   it otherwise; ``occlusion=False`` turns it off, ``occlusion=True`` without a shape is an error.

Per-candidate geometry is reported for every candidate, rejected or not: range, emission (Uz vs
V→camera), incidence (Uz vs Sun), phase (Sun vs V→camera) in degrees; the predicted pixel of V and
the resolution are NaN for a landmark behind the camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

import numpy as np

from spctool.errors import SpcUsageError

__all__ = [
    "CHECKS",
    "STATUS_OF_CHECK",
    "SelectOptions",
    "SelectResult",
    "field_of_view",
    "select_maplets",
]

#: check names in L15 order (keys of :attr:`SelectResult.checks`)
CHECKS = ("cone", "facing", "emission", "sunlit", "resolution", "size", "in_photo", "visible")

#: status word reported when a check is the first one a candidate fails (cli-contract.md)
STATUS_OF_CHECK = {
    "cone": "outside",
    "facing": "backfacing",
    "emission": "too-oblique",
    "sunlit": "unlit",
    "resolution": "too-coarse",
    "size": "too-big",
    "in_photo": "outside",
    "visible": "occluded",
}

_CONE_RHO = ("half-diagonal", "half-side")
_FW_SCALE = ("side", "half")
_NUMLM_MODES = ("deterministic", "spc_sequential")
_JACOBIANS = ("central", "analytic")
_EDGE_SAMPLES = 33  # points per photo edge used to find the half-diagonal field of view Λ_c


@dataclass
class SelectOptions:
    """Every threshold of Stage A (spc-algorithms.md §2.3, §13).

    ``occlusion``: None (default) = run the occlusion test when a shape is supplied, skip it
    otherwise; True = require it; False = never.  ``max_emission`` in degrees (None = no limit).
    ``reslm = inf`` disables the resolution screen; ``numlm = 0`` applies it to every candidate.
    """

    facing_cos_min: float = 0.05
    cone_rho: str = "half-diagonal"
    fractional_width: float = 0.5
    fw_scale: str = "side"
    numlm: int = 200
    reslm: float = 4.0
    numlm_mode: str = "deterministic"
    size_factor: float = 1.0
    occlusion: bool | None = None
    occlusion_tol: float = 0.01
    max_emission: float | None = None
    jacobian: str = "central"

    def __post_init__(self):
        def bad(msg):
            raise SpcUsageError(f"selection option {msg}")

        if self.cone_rho not in _CONE_RHO:
            bad(f"cone_rho must be one of {', '.join(_CONE_RHO)}, got {self.cone_rho!r}")
        if self.fw_scale not in _FW_SCALE:
            bad(f"fw_scale must be one of {', '.join(_FW_SCALE)}, got {self.fw_scale!r}")
        if self.numlm_mode not in _NUMLM_MODES:
            bad(f"numlm_mode must be one of {', '.join(_NUMLM_MODES)}, got {self.numlm_mode!r}")
        if self.jacobian not in _JACOBIANS:
            bad(f"jacobian must be one of {', '.join(_JACOBIANS)}, got {self.jacobian!r}")
        self.numlm = int(self.numlm)
        if self.numlm < 0:
            bad(f"numlm must be >= 0, got {self.numlm}")
        for name in ("facing_cos_min", "fractional_width", "reslm", "size_factor", "occlusion_tol"):
            value = float(getattr(self, name))
            if math.isnan(value):
                bad(f"{name} must be a number, got NaN")
            setattr(self, name, value)
        if not -1.0 <= self.facing_cos_min < 1.0:
            bad(f"facing_cos_min must be in [-1, 1), got {self.facing_cos_min}")
        if not 0.0 <= self.fractional_width < math.inf:
            bad(f"fractional_width must be >= 0, got {self.fractional_width}")
        if not self.reslm > 0.0:
            bad(f"reslm must be > 0, got {self.reslm}")
        if not self.size_factor > 0.0:
            bad(f"size_factor must be > 0, got {self.size_factor}")
        if not 0.0 <= self.occlusion_tol < math.inf:
            bad(f"occlusion_tol must be >= 0, got {self.occlusion_tol}")
        if self.max_emission is not None:
            self.max_emission = float(self.max_emission)
            if not 0.0 < self.max_emission <= 180.0:
                bad(f"max_emission must be in (0, 180] degrees, got {self.max_emission}")

    @classmethod
    def from_settings(cls, settings=None, **overrides) -> SelectOptions:
        """Defaults, then INIT_LITHOS ``NUMLM=``, ``RESLM=``, ``SIZLM=`` (-> ``size_factor``) when
        present (spc-formats.md §6.2), then ``overrides`` (None values are ignored)."""
        values: dict = {}
        if settings is not None:
            for key, name, conv in (
                ("numlm", "numlm", int),
                ("reslm", "reslm", float),
                ("sizlm", "size_factor", float),
            ):
                v = _setting(settings, key, conv)
                if v is not None:
                    values[name] = conv(v)
        known = {f.name for f in fields(cls)}
        for k, v in overrides.items():
            if k not in known:
                raise SpcUsageError(f"unknown selection option {k!r}")
            if v is not None:
                values[k] = v
        return cls(**values)

    def as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def _setting(settings, key: str, conv):
    """The value of INIT_LITHOS key ``KEY=`` only when the file sets it (Settings' own properties
    fall back to SPC defaults, which must not override spctool's options)."""
    getter = getattr(settings, "get_int" if conv is int else "get_float", None)
    if callable(getter):
        return getter(key.upper(), None)
    keys = getattr(settings, "keys", None)
    if isinstance(keys, dict):
        v = keys.get(key.upper(), keys.get(key.upper() + "="))
        return None if v is None else conv(float(str(v).replace("D", "E").replace("d", "e")))
    return None


@dataclass
class SelectResult:
    """Per-candidate outcome of :func:`select_maplets` (arrays of length N, candidate order).

    ``sample``/``line``: predicted SPC pixel of the landmark V; ``range_km``; ``resolution_km_px``
    (r_img); ``emission``, ``incidence``, ``phase`` in degrees; ``fraction_in_photo`` (fraction of the
    9 fine-test points in the photo); ``status``; ``selected``.  ``checks[name]`` is the pass mask of
    each check in :data:`CHECKS` (the resolution entry is r_img < RESLM·s_m whether or not the NUMLM
    rule applied it; ``resolution_applied`` says where it did; ``visible`` is True where the
    occlusion test did not run).  ``jacobian`` is J_xy (N, 2, 2) in pixels per maplet cell.
    """

    names: list[str]
    sample: np.ndarray
    line: np.ndarray
    range_km: np.ndarray
    resolution_km_px: np.ndarray
    emission: np.ndarray
    incidence: np.ndarray
    phase: np.ndarray
    fraction_in_photo: np.ndarray
    status: np.ndarray
    selected: np.ndarray
    checks: dict[str, np.ndarray] = field(default_factory=dict)
    resolution_applied: np.ndarray | None = None
    occlusion_tested: np.ndarray | None = None
    occlusion_checked: bool = False
    jacobian: np.ndarray | None = None
    boresight: np.ndarray | None = None
    half_fov_deg: float = math.nan
    options: SelectOptions | None = None

    def __len__(self) -> int:
        return len(self.names)

    @property
    def n_selected(self) -> int:
        return int(np.count_nonzero(self.selected))

    def status_counts(self) -> dict[str, int]:
        words, counts = np.unique(np.asarray(self.status, dtype=str), return_counts=True)
        return {str(w): int(c) for w, c in zip(words, counts)}

    def subset(self, mask) -> SelectResult:
        """The rows where ``mask`` is True (a bool array of length N)."""
        m = np.asarray(mask, bool)
        names = [n for n, k in zip(self.names, m) if k]

        def take(a):
            return None if a is None else np.asarray(a)[m]

        return replace(
            self,
            names=names,
            sample=self.sample[m],
            line=self.line[m],
            range_km=self.range_km[m],
            resolution_km_px=self.resolution_km_px[m],
            emission=self.emission[m],
            incidence=self.incidence[m],
            phase=self.phase[m],
            fraction_in_photo=self.fraction_in_photo[m],
            status=self.status[m],
            selected=self.selected[m],
            checks={k: v[m] for k, v in self.checks.items()},
            resolution_applied=take(self.resolution_applied),
            occlusion_tested=take(self.occlusion_tested),
            jacobian=take(self.jacobian),
        )

    def to_table(self, *, include_rejected: bool = False, picture=None, command=None, meta=None):
        """The landmark table (cli-contract.md): name, sample, line, range_km, resolution_km_px,
        emission, incidence, phase, fraction_in_photo, status — selected rows only unless
        ``include_rejected``."""
        from spctool.formats.table import LandmarkTable

        r = self if include_rejected else self.subset(self.selected)
        columns = {
            "name": list(r.names),
            "sample": np.asarray(r.sample, float),
            "line": np.asarray(r.line, float),
            "range_km": np.asarray(r.range_km, float),
            "resolution_km_px": np.asarray(r.resolution_km_px, float),
            "emission": np.asarray(r.emission, float),
            "incidence": np.asarray(r.incidence, float),
            "phase": np.asarray(r.phase, float),
            "fraction_in_photo": np.asarray(r.fraction_in_photo, float),
            "status": [str(s) for s in r.status],
        }
        return LandmarkTable(columns=columns, picture=picture, command=command, meta=dict(meta or {}))


# ------------------------------------------------------------------------------------------------
# geometry helpers
# ------------------------------------------------------------------------------------------------


def _unit_rows(a) -> np.ndarray:
    n = np.linalg.norm(a, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return a / n


def _angle_deg(cosines) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(cosines, -1.0, 1.0)))


def field_of_view(camera) -> tuple[np.ndarray, float]:
    """(b̂, Λ_c): the body-frame line of sight through the photo's centre point and the largest
    angle (rad) between it and the line of sight through any point of the photo boundary
    (L15 Eq. 3.1–3.5 with erratum 6; the boundary is sampled along its four edges so distortion
    models are honoured — for a pinhole camera the maximum is at a corner)."""
    npx, nln = float(camera.npx), float(camera.nln)
    t = np.linspace(0.0, 1.0, _EDGE_SAMPLES)
    s_edge = 1.0 + t * (npx - 1.0)
    l_edge = 1.0 + t * (nln - 1.0)
    samples = np.concatenate([s_edge, s_edge, np.ones_like(l_edge), np.full_like(l_edge, npx)])
    lines = np.concatenate([np.ones_like(s_edge), np.full_like(s_edge, nln), l_edge, l_edge])
    centre = camera.pixel_to_direction(np.array([(npx + 1.0) / 2.0]), np.array([(nln + 1.0) / 2.0]))[0]
    if not np.all(np.isfinite(centre)):
        raise SpcUsageError("the camera model cannot invert the photo's centre pixel")
    dirs = camera.pixel_to_direction(samples, lines)
    good = np.all(np.isfinite(dirs), axis=1)
    if not good.any():
        raise SpcUsageError("the camera model cannot invert the photo's boundary pixels")
    cosines = dirs[good] @ centre
    return centre, float(np.arccos(np.clip(cosines.min(), -1.0, 1.0)))


def _pixel_jacobian(camera, centres, ux, uy, scale, mode):
    """J_xy (N, 2, 2) in px per maplet cell: columns ∂/∂x (along Ux) and ∂/∂y (along Uy)."""
    if mode == "analytic":
        return camera.jacobian_maplet(centres, ux, uy, scale)
    step_x = scale[:, None] * ux
    step_y = scale[:, None] * uy
    pts = np.stack([centres + step_x, centres - step_x, centres + step_y, centres - step_y], axis=1)
    s, ln = camera.project(pts.reshape(-1, 3))
    s = s.reshape(-1, 4)
    ln = ln.reshape(-1, 4)
    jac = np.empty((centres.shape[0], 2, 2))
    jac[:, 0, 0] = (s[:, 0] - s[:, 1]) / 2.0  # L15 Eq. 3.15 with δ = one cell
    jac[:, 1, 0] = (ln[:, 0] - ln[:, 1]) / 2.0
    jac[:, 0, 1] = (s[:, 2] - s[:, 3]) / 2.0
    jac[:, 1, 1] = (ln[:, 2] - ln[:, 3]) / 2.0
    return jac


def _as_rows(a, n, name) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.shape == (3,):
        arr = np.broadcast_to(arr, (n, 3))
    if arr.shape != (n, 3):
        raise SpcUsageError(f"{name} must have shape ({n}, 3), got {arr.shape}")
    return np.ascontiguousarray(arr)


def _as_vector(a, n, name, dtype=np.float64) -> np.ndarray:
    arr = np.asarray(a, dtype=dtype)
    if arr.ndim == 0:
        arr = np.broadcast_to(arr, (n,))
    if arr.shape != (n,):
        raise SpcUsageError(f"{name} must have shape ({n},), got {arr.shape}")
    return arr


# ------------------------------------------------------------------------------------------------
# the stage
# ------------------------------------------------------------------------------------------------


def _checked_candidates(centres, ux, uy, uz, scale, qsz, names, sun):
    """The candidates as contiguous float rows (unit axes), scales, QSZ, N names and the unit Sun
    vector; a wrong shape, a non-positive scale, a negative QSZ or a zero Sun vector is a
    :class:`SpcUsageError`."""
    v_pts = np.asarray(centres, dtype=np.float64)
    if v_pts.ndim != 2 or v_pts.shape[1] != 3:
        raise SpcUsageError(f"centres must have shape (N, 3), got {v_pts.shape}")
    v_pts = np.ascontiguousarray(v_pts)
    n = v_pts.shape[0]
    ux = _unit_rows(_as_rows(ux, n, "ux"))
    uy = _unit_rows(_as_rows(uy, n, "uy"))
    uz = _unit_rows(_as_rows(uz, n, "uz"))
    scale = _as_vector(scale, n, "scale")
    qsz = _as_vector(qsz, n, "qsz", np.int64)
    if n and not (np.all(scale > 0) and np.all(qsz >= 0)):
        raise SpcUsageError("maplet scales must be > 0 and QSZ >= 0")
    names = [str(i) for i in range(n)] if names is None else [str(x) for x in names]
    if len(names) != n:
        raise SpcUsageError(f"{len(names)} names for {n} candidates")
    s_hat = np.asarray(sun, dtype=np.float64).reshape(3)
    s_norm = np.linalg.norm(s_hat)
    if not s_norm > 0:
        raise SpcUsageError("the Sun vector must be non-zero")
    return v_pts, ux, uy, uz, scale, qsz, names, s_hat / s_norm


def _box_inside(camera, v_pts, ux, uy, box_offset) -> np.ndarray:
    """(N, 9) whether each point of the candidate's 3×3 box (centre ± ``box_offset`` along Ux, Uy)
    projects into the picture in front of the camera (L15 Eq. 3.17, erratum 11)."""
    n = v_pts.shape[0]
    if not n:
        return np.zeros((0, 9), bool)
    kk, jj = np.meshgrid([-1.0, 0.0, 1.0], [-1.0, 0.0, 1.0], indexing="ij")
    kk = kk.reshape(-1)
    jj = jj.reshape(-1)
    off = box_offset[:, None, None] * (
        kk[None, :, None] * ux[:, None, :] + jj[None, :, None] * uy[:, None, :]
    )
    bs, bl, bf = camera.project_with_mask((v_pts[:, None, :] + off).reshape(-1, 3))
    return (bf & camera.in_image(bs, bl)).reshape(n, 9)


def _first_failed(effective, n):
    """(status (N,) object, selected (N,)): each candidate's status names the first check of
    :data:`CHECKS` it fails, ``"ok"`` if none."""
    status = np.full(n, "ok", dtype=object)
    decided = np.zeros(n, bool)
    for name in CHECKS:
        fail = ~effective[name] & ~decided
        status[fail] = STATUS_OF_CHECK[name]
        decided |= fail
    return status, ~decided


def select_maplets(
    camera, sun, centres, ux, uy, uz, scale, qsz, names=None, options: SelectOptions | None = None, shape=None
) -> SelectResult:
    """Stage A: test N candidate maplets against one picture (module docstring for the checks).

    ``camera``: :class:`spctool.geometry.camera.Camera`; ``sun``: body→Sun vector (3,) (normalised
    here); ``centres`` V (N, 3) km and ``ux``, ``uy``, ``uz`` (N, 3) unit axes, body frame;
    ``scale`` (N,) km per cell; ``qsz`` (N,) half-size in cells; ``names`` (N,) (default ``"0"``,
    ``"1"`` …); ``shape``: a geometry shape with ``first_hit`` and ``max_diameter``
    (:class:`~spctool.geometry.shape.PatchShape` / :class:`~spctool.geometry.shape.TriangleShape`)
    or None.  Candidate order matters only for ``numlm_mode="spc_sequential"``.
    """
    opts = options if options is not None else SelectOptions()
    v_pts, ux, uy, uz, scale, qsz, names, s_hat = _checked_candidates(
        centres, ux, uy, uz, scale, qsz, names, sun
    )
    n = v_pts.shape[0]
    if opts.occlusion is True and shape is None:
        raise SpcUsageError("the occlusion test needs a shape model")
    run_occlusion = shape is not None and opts.occlusion is not False

    boresight, lam_c = field_of_view(camera)
    position = np.asarray(camera.position, dtype=np.float64)

    # line of sight spacecraft → landmark (L15 Eq. 3.6, 3.7)
    los = v_pts - position
    rng = np.linalg.norm(los, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        v_hat = los / rng[:, None]
    d_m = (2.0 * qsz + 1.0) * scale
    fw = d_m if opts.fw_scale == "side" else d_m / 2.0
    box_offset = fw * opts.fractional_width  # offset of the outer fine-test points along Ux, Uy

    # 1. cone (L15 Eq. 3.8–3.11, errata 7 and 8)
    rho = d_m / math.sqrt(2.0) if opts.cone_rho == "half-diagonal" else d_m / 2.0
    rho = np.maximum(rho, box_offset * math.sqrt(2.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        lam_m = np.where(rng > rho, np.arcsin(np.clip(rho / rng, 0.0, 1.0)), np.pi)
    cos_limit = np.cos(np.minimum(lam_c + lam_m, np.pi))
    cone = (v_hat @ boresight > cos_limit) | (lam_c + lam_m >= np.pi)

    # 2. facing the camera (Eq. 3.12); 3. emission limit
    cos_e = -np.einsum("ij,ij->i", v_hat, uz)
    facing = cos_e > opts.facing_cos_min
    if opts.max_emission is None:
        emission_ok = np.ones(n, bool)
    else:
        emission_ok = cos_e > math.cos(math.radians(opts.max_emission))
    # 4. sunlight (Eq. 3.13)
    cos_i = uz @ s_hat
    sunlit = cos_i > 0.0

    # geometry for the report; points behind the camera get NaN pixels
    in_front = camera.in_front(v_pts) if n else np.zeros(0, bool)
    sample, line = camera.project(v_pts) if n else (np.zeros(0), np.zeros(0))
    sample = np.where(in_front, sample, np.nan)
    line = np.where(in_front, line, np.nan)
    emission = _angle_deg(cos_e)
    incidence = _angle_deg(cos_i)
    phase = _angle_deg(-(v_hat @ s_hat))

    # 5. resolution (Eq. 3.14, 3.15; errata 9, 10)
    if n:
        jac = _pixel_jacobian(camera, v_pts, ux, uy, scale, opts.jacobian)
    else:
        jac = np.zeros((0, 2, 2))
    det = np.abs(jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        r_img = np.where(in_front & (det > 0), scale / np.sqrt(det), np.nan)
    resolution_ok = r_img < opts.reslm * scale  # NaN compares False

    # 6. size (Eq. 3.16)
    size_ok = d_m < r_img * min(camera.npx, camera.nln) * opts.size_factor

    # 7. fine in-photo test with the 3×3 box (Eq. 3.17, erratum 11)
    inside = _box_inside(camera, v_pts, ux, uy, box_offset)
    fraction = inside.mean(axis=1) if n else np.zeros(0)
    in_photo = inside.any(axis=1)

    # 8. occlusion (§3.2.1): one batched ray query over the candidates still in the running
    visible = np.ones(n, bool)
    before_occlusion = cone & facing & emission_ok & sunlit & size_ok & in_photo
    tested = before_occlusion & run_occlusion
    if tested.any():
        from spctool.geometry.shape import visible_from

        tol = opts.occlusion_tol * float(shape.max_diameter)
        visible[tested] = visible_from(shape, position, v_pts[tested], tol)

    # NUMLM rule for the resolution screen
    passes_others = before_occlusion & visible
    if opts.numlm_mode == "deterministic":
        applied = np.full(n, int(passes_others.sum()) > opts.numlm)
    else:
        earlier = np.cumsum(passes_others) - passes_others
        applied = earlier >= opts.numlm
    resolution_pass = resolution_ok | ~applied

    checks = {
        "cone": cone,
        "facing": facing,
        "emission": emission_ok,
        "sunlit": sunlit,
        "resolution": resolution_ok,
        "size": size_ok,
        "in_photo": in_photo,
        "visible": visible,
    }
    effective = dict(checks, resolution=resolution_pass)
    status, selected = _first_failed(effective, n)

    return SelectResult(
        names=names,
        sample=sample,
        line=line,
        range_km=rng,
        resolution_km_px=r_img,
        emission=emission,
        incidence=incidence,
        phase=phase,
        fraction_in_photo=fraction,
        status=status.astype(str) if n else np.zeros(0, dtype="<U1"),
        selected=selected,
        checks=checks,
        resolution_applied=applied,
        occlusion_tested=tested,
        occlusion_checked=run_occlusion,
        jacobian=jac,
        boresight=boresight,
        half_fov_deg=math.degrees(lam_c),
        options=opts,
    )
