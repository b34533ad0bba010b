"""The SPC camera model of a picture: projection, inverse and analytic Jacobians.

Forward model (spc-formats.md §2.5 steps 1–5 and §6.4; spc-algorithms.md §1.3), for a body-fixed
point P (km):

1. u = SCOBJ + P (SCOBJ: spacecraft → body centre, body frame; the spacecraft position is −SCOBJ);
2. z = R·u with R = rows (CX, CY, CZ), the body→camera rotation;
3. normalised focal plane (x̄, ȳ) = (z₁/z₃, z₂/z₃); the distortion model maps it to the distorted
   focal plane in mm (undistorted → distorted).  Without a ``DISTORT=`` model: (x, y) = MMFL·(x̄, ȳ).
   With one, the common step is (x, y) = (1 + P0)·MMFL·(x̄, ȳ) followed by the model (§6.4):

   * ``OWEN`` (SPC order P1…P6, spc-algorithms.md §1.4):
     Δx = −P1·y·r + P2·x·r² − P3·y·r³ + P4·x·r⁴ + P5·x·y + P6·x²,
     Δy = +P1·x·r + P2·y·r² + P3·x·r³ + P4·y·r⁴ + P5·y² + P6·x·y;
   * ``RADIAL``: (x, y)·(1 + P1·r² + P2·r⁴);
   * ``CUBIC``: x' = Σₖ₌₁..₁₀ Pₖ·mₖ, y' = Σₖ₌₁..₁₀ Pₖ₊₁₀·mₖ, m = (1, x, y, x², xy, y², x³, x²y, xy², y³);
   * ``APOLLO``: ρ = r²; (x, y)·(1 + P1ρ + P2ρ² + P3ρ³), then t = P4ρ + P5ρ², x' += t·sin P6, y' −= t·cos P6;
   * ``HIRISE``: (x − P1, y − P2);
   * ``LINESCAN`` (focal-plane part only): x = (1 + P0)·MMFL·x̄, R = √(x² + P1²), x' = x(1 + P2R² + P3R³),
     y' = MMFL·ȳ (unscaled).  The per-line pose polynomials of line-scan pictures (spc-formats.md §2.4)
     are **not** modelled: a :class:`Camera` has one pose.
4. legacy SUM ``DISTORTION`` terms: (x, y)·(1 + D1), then (x, y)·(1 + D2·r² + D3·y + D4·x) with r, x, y
   taken after the D1 scaling;
5. sample = CTR1 + K11·x + K12·y + K13·x·y, line = CTR2 + K21·x + K22·y + K23·x·y (1-based SPC pixels,
   no clipping; the K x·y column is kept, spc-formats.md §8 item 8).

The whole chain (x̄, ȳ) → (sample, line) is evaluated per point, with its 2×2 derivative, in small
numba kernels (:mod:`spctool.geometry._camerakernels`); the Jacobians are chained from it:

* ∂(x̄, ȳ)/∂x_C = (1/z₃)·[[1, 0, −x̄], [0, 1, −ȳ]] — L15 Eq. 2.24 with erratum 2 (third column −x_C, −y_C);
* ∂x_C/∂P = R; ∂x_C/∂(spacecraft position) = −R (L15 Eq. 2.26/2.27 with erratum 3: −T_C^B);
* ∂x_C/∂δθ = [x_C×] for the update T⁺ = Rot(−δθ)·T (erratum 3; :func:`frames.apply_attitude_update`);
* the distortion derivative is written directly from the SPC-order formulas (erratum 4 does not arise).

The inverse (:meth:`Camera.pixel_to_focal`) replaces SPC's 20-step fixed-point PXMM iteration
(spc-formats.md §2.5 step 6) by a damped Newton iteration on the full 2×2 map, run per point until the
pixel residual is below ``tol`` (default 1e-10 px); points that do not converge are reported.

Speed: the kernels are compiled by numba on first use and cached (``cache=True``) in ``__pycache__``;
a cold compile of the three kernels takes roughly 10–15 s once per machine and source change.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from spctool.errors import SpcUsageError
from spctool.geometry._camerakernels import (
    _k_cubic_cells,
    _k_invert,
    _k_jac_camera,
    _k_polish,
    _k_project_body,
)
from spctool.geometry._cubicgrid import _k_cubic, _k_cubic_lattice
from spctool.geometry.frames import apply_attitude_update, skew

__all__ = ["Camera", "MODELS", "ProjectionJacobians", "model_code"]

#: distortion models implemented, with the kernel code of each
MODELS = {"NONE": 0, "OWEN": 1, "RADIAL": 2, "CUBIC": 3, "APOLLO": 4, "HIRISE": 5, "LINESCAN": 6}
#: coefficients handed to the kernels (CUBIC uses P0…P20); missing coefficients count as 0
_NCOEF = 21
# The kernels receive every constant as one tuple of floats ``q`` (scalars, so that LLVM keeps them in
# registers; array loads inside the loops could not be hoisted because the outputs might alias them):
#   q[0] MMFL, q[1:3] CTR, q[3:9] K11 K12 K13 K21 K22 K23, q[9:13] D1…D4, q[13 + k] = P_k (k = 0…20).
_NQ = 13 + _NCOEF


def model_code(name: str) -> int:
    """Kernel code of a distortion-model name (case-insensitive); SpcUsageError if not implemented."""
    key = (name or "NONE").strip().upper()
    if key not in MODELS:
        raise SpcUsageError(
            f"camera distortion model {name!r} is not implemented (known: {', '.join(MODELS)}); "
            "SPC's USGS, OPENCV and HAYA2 models have no public equations"
        )
    return MODELS[key]


# --------------------------------------------------------------------------------------------------
# Camera
# --------------------------------------------------------------------------------------------------


class ProjectionJacobians(NamedTuple):
    """Everything a pose or landmark solver needs from one pass over N points."""

    sample: np.ndarray  # (N,)
    line: np.ndarray  # (N,)
    camera_points: np.ndarray  # (N, 3) x_C = R·(P + SCOBJ)
    camera: np.ndarray  # (N, 2, 3) ∂(sample, line)/∂x_C
    position: np.ndarray  # (N, 2, 3) ∂/∂(spacecraft position, body frame) = −camera·R
    attitude: np.ndarray  # (N, 2, 3) ∂/∂δθ for T⁺ = Rot(−δθ)·T, = camera·[x_C×]
    point: np.ndarray  # (N, 2, 3) ∂/∂(landmark body position) = camera·R


_EYE = np.eye(3)
#: :meth:`Camera.pixel_to_direction_lattice`'s grids by (intrinsics but CTR, step, tolerance, node range):
#: (x̄, ȳ of the nodes, good cells, their count); least recently used dropped beyond the size below
_LATTICE_GRIDS: OrderedDict = OrderedDict()
_LATTICE_GRIDS_MAX = 256
_LATTICE_LOCK = threading.Lock()
_ZERO3 = np.zeros(3)
# read-only like the Camera's own arrays, so the kernels see one array type (one compilation)
_EYE.flags.writeable = False
_ZERO3.flags.writeable = False


def _f64(a, shape=None, name="array") -> np.ndarray:
    out = np.array(a, dtype=np.float64, copy=True)
    if shape is not None and out.shape != shape:
        raise SpcUsageError(f"camera {name} must have shape {shape}, got {out.shape}")
    out.flags.writeable = False
    return out


def _flat(a) -> np.ndarray:
    """1-D, C-contiguous, writable float64 (one array type for the kernels: one compilation)."""
    if type(a) is np.ndarray and a.ndim == 1 and a.dtype == np.float64 and a.flags.c_contiguous:
        return a if a.flags.writeable else a.copy()  # already so (a template's sub-ray lattice)
    out = np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(-1))
    return out if out.flags.writeable else out.copy()


def _points(points) -> tuple[np.ndarray, tuple]:
    p = np.asarray(points, dtype=np.float64)
    if p.shape[-1:] != (3,):
        raise ValueError(f"expected points with a last axis of length 3, got shape {p.shape}")
    lead = p.shape[:-1]
    p = np.ascontiguousarray(p.reshape(-1, 3))
    if not p.flags.writeable:  # keep one array type for the kernels (avoids a second compilation)
        p = p.copy()
    return p, lead


@dataclass(frozen=True, eq=False)
class Camera:
    """Intrinsics and pose of one SPC picture (spc-formats.md §2.5, §6.4).

    Arrays are stored as read-only float64 copies.  ``rotation`` is body→camera (rows CX, CY, CZ);
    ``scobj`` is the SUM SCOBJ (spacecraft → body centre, body frame, km); ``coefficients`` are the
    ``DISTORT=`` values P0…PJ in SPC order (missing trailing coefficients count as 0).
    """

    mmfl: float
    ctr: np.ndarray
    kmatrix: np.ndarray
    rotation: np.ndarray
    scobj: np.ndarray
    npx: int
    nln: int
    legacy_d: np.ndarray = field(default_factory=lambda: np.zeros(4))
    model: str = "NONE"
    coefficients: np.ndarray = field(default_factory=lambda: np.zeros(0))
    name: str = ""

    def __post_init__(self):
        set_ = object.__setattr__
        set_(self, "mmfl", float(self.mmfl))
        set_(self, "ctr", _f64(self.ctr, (2,), "ctr"))
        set_(self, "kmatrix", _f64(self.kmatrix, (2, 3), "kmatrix"))
        set_(self, "rotation", _f64(self.rotation, (3, 3), "rotation"))
        set_(self, "scobj", _f64(self.scobj, (3,), "scobj"))
        set_(self, "npx", int(self.npx))
        set_(self, "nln", int(self.nln))
        d = np.zeros(4) if self.legacy_d is None else self.legacy_d
        set_(self, "legacy_d", _f64(d, (4,), "legacy_d"))
        code = model_code(self.model)
        set_(self, "model", (self.model or "NONE").strip().upper())
        coef = _f64(np.zeros(0) if self.coefficients is None else self.coefficients, None, "coefficients")
        if coef.ndim != 1 or coef.size > 101:
            raise SpcUsageError(f"camera coefficients must be P0…PJ with J ≤ 100, got shape {coef.shape}")
        set_(self, "coefficients", coef)
        packed = np.zeros(_NCOEF)
        if code != 0:
            used = min(coef.size, _NCOEF)
            packed[:used] = coef[:used]
        q = np.concatenate([[self.mmfl], self.ctr, self.kmatrix.reshape(6), self.legacy_d, packed])
        set_(self, "_code", code)
        set_(self, "_q", tuple(float(v) for v in q))
        # start of the inverse: (x̄, ȳ) = g·K₂⁻¹·(sample − CTR1, line − CTR2), K₂ = K's 2×2 block
        k2 = self.kmatrix[:, :2]
        if np.linalg.det(k2) == 0.0:
            raise SpcUsageError("camera K-matrix 2×2 block is singular")
        kinv = np.linalg.inv(k2)
        g = 1.0 / (self.mmfl * (1.0 + self.legacy_d[0]) * (1.0 + packed[0] if code != 0 else 1.0))
        set_(self, "_guess", (float(kinv[0, 0]), float(kinv[0, 1]), float(kinv[1, 0]), float(kinv[1, 1]), g))

    # ---- construction ---------------------------------------------------------------------------

    @classmethod
    def from_picture(cls, picture, settings=None, *, picture_name: str | None = None) -> Camera:
        """Camera of a SUM ``Picture``; ``settings`` (INIT_LITHOS) supplies a matching ``DISTORT=`` model.

        The model is the one for ``picture_name`` -- the picture SPC was asked for, whose SUM file is
        SUMFILES/<name>.SUM: getmm (xCommon.f) is called with that PICNM, not with SUM line 1 (a renamed
        or copied picture) -- else for the name on line 1.  The legacy SUM ``DISTORTION`` values
        (``picture.distortion``, None when the line is absent) are applied as well (spc-formats.md §2.5
        step 4).
        """
        model, coef = "NONE", np.zeros(0)
        if getattr(picture, "is_linescan", False):
            raise SpcUsageError(
                f"picture {getattr(picture, 'name', '')} is a line-scan (pushbroom) picture (column 14 'L', "
                "LINE SCAN DATA): this command needs a frame camera and refuses it "
                "(its projection is spctool.geometry.linescan.project_linescan)"
            )
        if settings is not None:
            dm = settings.distortion_for(picture_name if picture_name is not None else picture.name)
            # getmm (xCommon.f): the last matching template wins, and its TYPE is compared exactly
            # (IF(TYPE(JD).EQ.'OWEN') ...); a name it does not know ('owen', ' OWEN', PINHOLE, OPENCV) falls
            # through to the plain pinhole z = MMFL*(z1/z3, z2/z3), without P0
            if dm is not None and dm.model in MODELS and dm.model != "NONE":
                model, coef = dm.model, np.asarray(dm.coefficients, dtype=np.float64)
        d = getattr(picture, "distortion", None)
        return cls(
            mmfl=picture.mmfl,
            ctr=picture.ctr,
            kmatrix=picture.kmatrix,
            rotation=picture.rotation,
            scobj=picture.scobj,
            npx=picture.npx,
            nln=picture.nln,
            legacy_d=np.zeros(4) if d is None else d,
            model=model,
            coefficients=coef,
            name=getattr(picture, "name", ""),
        )

    @property
    def position(self) -> np.ndarray:
        """Body-frame spacecraft position (km) = −SCOBJ."""
        return -self.scobj

    def with_pose(self, *, scobj=None, rotation=None, position=None) -> Camera:
        """Copy with a new pose: give ``scobj`` or ``position`` (= −scobj), and/or ``rotation``."""
        if scobj is not None and position is not None:
            raise SpcUsageError("give scobj or position, not both")
        changes = {}
        if position is not None:
            changes["scobj"] = -np.asarray(position, dtype=np.float64)
        if scobj is not None:
            changes["scobj"] = scobj
        if rotation is not None:
            changes["rotation"] = rotation
        return dataclasses.replace(self, **changes)

    def with_ctr(self, ctr) -> Camera:
        """Copy with the optical centre CTR moved to ``ctr`` (everything else shared; no re-validation:
        ``dataclasses.replace(self, ctr=ctr)`` field for field, without re-packing the model)."""
        ctr = _f64(ctr, (2,), "ctr")
        out = object.__new__(type(self))  # copy.copy's result without its reduce protocol (~10 µs a render)
        out.__dict__.update(self.__dict__)
        set_ = object.__setattr__
        set_(out, "ctr", ctr)
        set_(out, "_q", (self._q[0], float(ctr[0]), float(ctr[1])) + self._q[3:])
        return out

    def updated(self, dposition=None, dtheta=None) -> Camera:
        """Copy after a pose-solver step: position += dposition; T⁺ = Rot(−δθ)·T.

        The attitude update is :func:`spctool.geometry.frames.apply_attitude_update`, the convention of
        :meth:`jacobian_attitude`.
        """
        pos = self.position if dposition is None else self.position + np.asarray(dposition, dtype=np.float64)
        rot = self.rotation if dtheta is None else apply_attitude_update(self.rotation, dtheta)
        return self.with_pose(position=pos, rotation=rot)

    # ---- derived quantities ---------------------------------------------------------------------

    @property
    def ifov(self) -> float:
        """Instantaneous field of view (rad/px) = 1/(MMFL·√|K11·K22|) (spc-formats.md §2.5 step 7)."""
        return 1.0 / (self.mmfl * math.sqrt(abs(self.kmatrix[0, 0] * self.kmatrix[1, 1])))

    @property
    def half_fov(self) -> tuple[float, float]:
        """Approximate half field of view (rad): (NPX/(2·|K11|·MMFL), NLN/(2·|K22|·MMFL)) (§2.5 step 7)."""
        return (
            self.npx / (2.0 * abs(self.kmatrix[0, 0]) * self.mmfl),
            self.nln / (2.0 * abs(self.kmatrix[1, 1]) * self.mmfl),
        )

    @property
    def boresight(self) -> np.ndarray:
        """Camera +z axis (CZ) in the body frame."""
        return self.rotation[2].copy()

    def resolution(self, points, normals=None) -> np.ndarray:
        """Ground resolution (km/px) = range·IFOV / cos(emission); cos(emission) = 1 when normals is None."""
        p, lead = _points(points)
        los = p - self.position
        rng = np.linalg.norm(los, axis=-1)
        res = rng * self.ifov
        if normals is not None:
            n = np.broadcast_to(np.asarray(normals, dtype=np.float64), lead + (3,)).reshape(-1, 3)
            mu = -np.sum(n * los, axis=-1) / (rng * np.linalg.norm(n, axis=-1))
            res = res / mu
        return res.reshape(lead)

    def in_image(self, sample, line) -> np.ndarray:
        """1 ≤ sample ≤ NPX and 1 ≤ line ≤ NLN (spc-formats.md §2.5 step 5)."""
        s = np.asarray(sample)
        ln = np.asarray(line)
        return (s >= 1.0) & (s <= self.npx) & (ln >= 1.0) & (ln <= self.nln)

    # ---- frames ---------------------------------------------------------------------------------

    def to_camera(self, points) -> np.ndarray:
        """Camera-frame vectors x_C = R·(P + SCOBJ) of body-fixed points (..., 3)."""
        p = np.asarray(points, dtype=np.float64)
        return (p + self.scobj) @ self.rotation.T

    def in_front(self, points) -> np.ndarray:
        """z_C > 0 for body-fixed points (..., 3)."""
        p = np.asarray(points, dtype=np.float64)
        return (p + self.scobj) @ self.rotation[2] > 0.0

    # ---- forward --------------------------------------------------------------------------------

    def project_with_mask(self, points):
        """(sample, line, in_front) of body-fixed points (..., 3); no clipping."""
        p, lead = _points(points)
        n = p.shape[0]
        smp = np.empty(n)
        lin = np.empty(n)
        front = np.empty(n, dtype=np.bool_)
        _k_project_body(p, self.rotation, self.scobj, self._q, self._code, smp, lin, front)
        return smp.reshape(lead), lin.reshape(lead), front.reshape(lead)

    def project(self, points):
        """(sample, line) of body-fixed points (..., 3): 1-based SPC pixels, no clipping.

        Points behind the camera still get a (meaningless) pixel; use :meth:`project_with_mask` or
        :meth:`in_front` to tell them apart.
        """
        smp, lin, _ = self.project_with_mask(points)
        return smp, lin

    def project_camera_frame(self, points_cam):
        """(sample, line) of camera-frame vectors (..., 3)."""
        z, lead = _points(points_cam)
        n = z.shape[0]
        smp = np.empty(n)
        lin = np.empty(n)
        front = np.empty(n, dtype=np.bool_)
        _k_project_body(z, _EYE, _ZERO3, self._q, self._code, smp, lin, front)
        return smp.reshape(lead), lin.reshape(lead)

    def focal_to_pixel(self, xn, yn, *, jacobian: bool = False):
        """Normalised focal plane (x̄, ȳ) = (z₁/z₃, z₂/z₃) → (sample, line).

        With ``jacobian=True`` also returns ∂(sample, line)/∂(x̄, ȳ) with shape (..., 2, 2).
        """
        xn, yn = np.broadcast_arrays(np.asarray(xn, dtype=np.float64), np.asarray(yn, dtype=np.float64))
        lead = xn.shape
        z = np.empty(xn.shape + (3,))
        z[..., 0] = xn
        z[..., 1] = yn
        z[..., 2] = 1.0
        if not jacobian:
            return self.project_camera_frame(z)
        smp, lin, jac = self._camera_jacobian_flat(z.reshape(-1, 3))
        return smp.reshape(lead), lin.reshape(lead), jac[:, :, :2].reshape(lead + (2, 2))

    # ---- inverse --------------------------------------------------------------------------------

    def _invert(self, sample, line, rot, tol, max_iter):
        s, ln = np.broadcast_arrays(np.asarray(sample, dtype=np.float64), np.asarray(line, dtype=np.float64))
        lead = s.shape
        sf = _flat(s)
        lf = _flat(ln)
        n = sf.size
        xn = np.empty(n)
        yn = np.empty(n)
        dirs = np.empty((n, 3))
        nit = np.empty(n, dtype=np.int64)
        _k_invert(sf, lf, self._q, self._code, self._guess, float(tol), int(max_iter), rot, xn, yn, dirs, nit)
        return xn.reshape(lead), yn.reshape(lead), dirs.reshape(lead + (3,)), nit.reshape(lead)

    def pixel_to_focal(
        self, sample, line, *, tol: float = 1e-10, max_iter: int = 50, return_iterations: bool = False
    ):
        """Normalised focal plane (x̄, ȳ) whose projection is (sample, line); vectorised.

        Replaces SPC's fixed-point PXMM (spc-formats.md §2.5 step 6) by Newton on the full 2×2 map
        (distortion + legacy D + K) per point, with step halving, until the pixel residual
        max(|Δsample|, |Δline|) ≤ ``tol``.  Points that do not converge within ``max_iter`` steps (no
        preimage: the model folds there) give NaN.  ``return_iterations`` adds the step count per point.
        """
        xn, yn, _, nit = self._invert(sample, line, _EYE, tol, max_iter)
        return (xn, yn, nit) if return_iterations else (xn, yn)

    def pixel_to_camera_direction(
        self, sample, line, *, tol: float = 1e-10, max_iter: int = 50
    ) -> np.ndarray:
        """Unit line of sight (..., 3) in the camera frame (z_C > 0); NaN where not invertible."""
        return self._invert(sample, line, _EYE, tol, max_iter)[2]

    def pixel_to_direction(self, sample, line, *, tol: float = 1e-10, max_iter: int = 50) -> np.ndarray:
        """Unit line of sight (..., 3) in the body frame for pixels (sample, line); NaN where not invertible.

        The ray is P(t) = position + t·direction, t > 0.
        """
        return self._invert(sample, line, self.rotation, tol, max_iter)[2]

    def pixel_to_direction_grid(
        self, sample, line, *, grid_step: float = 4.0, max_move: float = 1e-3, interp_tol: float = 1e-7
    ):
        """:meth:`pixel_to_direction` for many points of a small region (a template window's sub-rays).

        The distortion is inverted exactly (Newton, 1e-10 px) only on a grid of nodes ``grid_step`` px
        apart over the points' bounding box (one node beyond it on each side).  In the grid cells where the
        bicubic (tensor cubic Lagrange) interpolant of those inverses reproduces the pixel to ``interp_tol``
        px at the centre and quarter points of the cell and of its neighbours (:func:`_k_cubic_cells`),
        a point takes the interpolant as it is (no Newton step; ≤ 1e-7 px from the exact inverse on the
        cameras of ``tests/test_camera.py``).  Elsewhere (e.g. next to the optical axis, where OWEN's odd
        terms are not smooth) a point starts from the bilinear interpolation of its cell's nodes and
        takes one Newton step on the full map (``interp_tol < 0``: everywhere).  The seed
        is within ``max_move`` px of the answer (else the point gets the full iteration), so after the
        step the residual is of order (curvature of the map)·``max_move``² — far below 1e-10 px for the
        smooth models here (``tests/test_camera.py`` checks both against :meth:`pixel_to_direction`).
        NaN for a point whose sample or line is not finite.
        """
        s, ln = np.broadcast_arrays(np.asarray(sample, dtype=np.float64), np.asarray(line, dtype=np.float64))
        lead = s.shape
        sf = _flat(s)
        lf = _flat(ln)
        if sf.size == 0:
            return np.empty(lead + (3,))
        finite = np.isfinite(sf) & np.isfinite(lf)
        if not finite.all():  # a point that is not finite has no direction (NaN); the grid spans the others
            dirs = np.full((sf.size, 3), np.nan)
            if finite.any():
                dirs[finite] = self.pixel_to_direction_grid(
                    sf[finite], lf[finite], grid_step=grid_step, max_move=max_move, interp_tol=interp_tol
                )
            return dirs.reshape(lead + (3,))
        grid = self._inverse_grid(sf, lf, grid_step)
        dirs = np.empty((sf.size, 3))
        redo = np.ones(sf.size, dtype=np.bool_)
        good = np.empty(grid[0].shape, dtype=np.bool_)
        if _k_cubic_cells(self._q, self._code, *grid, float(interp_tol), good):
            _k_cubic(sf, lf, *grid, good, self.rotation, dirs, redo)
        self._polish(sf, lf, grid, float(max_move), dirs, redo)
        return dirs.reshape(lead + (3,))

    def _polish(self, sf, lf, grid, max_move, dirs, redo):
        """Directions of the points ``redo`` (1-D ``sf``, ``lf``; ``dirs`` (N, 3)): one Newton step from the
        grid's bilinear seed, the full iteration where that is not exact."""
        if not redo.any():
            return
        idx = None if redo.all() else np.flatnonzero(redo)
        ps, pl = (sf, lf) if idx is None else (sf[idx], lf[idx])
        pd = np.empty((ps.size, 3))
        again = np.empty(ps.size, dtype=np.bool_)
        _k_polish(ps, pl, self._q, self._code, *grid, max_move, self.rotation, pd, again)
        if again.any():
            pd[again] = self._invert(ps[again], pl[again], self.rotation, 1e-10, 50)[2]
        if idx is None:
            dirs[:] = pd
        else:
            dirs[idx] = pd

    def _inverse_grid(self, sf, lf, grid_step):
        """(x̄, ȳ of the nodes (ns, nl), s0, l0, step): exact inverses on nodes ``grid_step`` apart over
        the bounding box of the points, one node beyond it on each side."""
        step = float(grid_step)
        s0 = float(np.nanmin(sf)) - step - 1e-9
        l0 = float(np.nanmin(lf)) - step - 1e-9
        ns = int(math.floor((float(np.nanmax(sf)) - s0) / step)) + 3
        nl = int(math.floor((float(np.nanmax(lf)) - l0) / step)) + 3
        gs, gl = np.meshgrid(s0 + step * np.arange(ns), l0 + step * np.arange(nl), indexing="ij")
        gxn, gyn, _, _ = self._invert(gs, gl, _EYE, 1e-10, 50)
        return _flat(gxn).reshape(ns, nl), _flat(gyn).reshape(ns, nl), s0, l0, step

    def pixel_to_direction_lattice(self, samples, lines, *, grid_step: float = 4.0, interp_tol: float = 1e-7):
        """:meth:`pixel_to_direction_grid` of every (sample, line) of ``lines`` × ``samples`` (1-D), as a
        (len(lines), len(samples), 3) array — a template window's sub-ray lattice — within 1e-7 px of
        :meth:`pixel_to_direction` like it.  The grid's nodes sit at CTR + k·``grid_step`` and depend on
        the intrinsics but neither on CTR nor on the pose, so the inverses and the choice of cells are
        kept (:data:`_LATTICE_GRIDS`, a few hundred windows) for the next window with the same nodes —
        a template re-rendered with its CTR moved by a fraction of a pixel; the bicubic path then costs
        4 + 4 products per point."""
        sf = _flat(samples)
        lf = _flat(lines)
        # the extremes, all finite exactly when every point is (a NaN propagates to both); empty or not
        # finite: the general grid path, point by point
        ext = (sf.min(), sf.max(), lf.min(), lf.max()) if sf.size and lf.size else (math.nan,)
        if not all(map(math.isfinite, ext)):
            ss, ll = np.meshgrid(sf, lf)
            return self.pixel_to_direction_grid(ss, ll, grid_step=grid_step, interp_tol=interp_tol)
        s_lo, s_hi, l_lo, l_hi = map(float, ext)
        step = float(grid_step)
        c1, c2 = float(self.ctr[0]), float(self.ctr[1])
        ka = math.floor((s_lo - c1) / step) - 1
        kb = math.floor((s_hi - c1) / step) + 2
        ja = math.floor((l_lo - c2) / step) - 1
        jb = math.floor((l_hi - c2) / step) + 2
        key = (self._code, self._q[0], self._q[3:], step, float(interp_tol), ka, kb, ja, jb)
        with _LATTICE_LOCK:
            hit = _LATTICE_GRIDS.get(key)
            if hit is not None:
                _LATTICE_GRIDS.move_to_end(key)
        if hit is None:  # exact inverses of the camera with CTR = 0 (the same nodes whatever the CTR)
            canon = self.with_ctr([0.0, 0.0])
            gs, gl = np.meshgrid(step * np.arange(ka, kb + 1), step * np.arange(ja, jb + 1), indexing="ij")
            gxn, gyn, _, _ = canon._invert(gs, gl, _EYE, 1e-10, 50)
            gxn = _flat(gxn).reshape(gs.shape)
            gyn = _flat(gyn).reshape(gs.shape)
            good = np.empty(gs.shape, dtype=np.bool_)
            ngood = _k_cubic_cells(
                canon._q, canon._code, gxn, gyn, ka * step, ja * step, step, float(interp_tol), good
            )
            hit = gxn, gyn, good, ngood
            with _LATTICE_LOCK:
                _LATTICE_GRIDS[key] = hit
                while len(_LATTICE_GRIDS) > _LATTICE_GRIDS_MAX:
                    _LATTICE_GRIDS.popitem(last=False)
        gxn, gyn, good, ngood = hit
        grid = (gxn, gyn, c1 + ka * step, c2 + ja * step, step)
        dirs = np.empty((lf.size, sf.size, 3))
        if ngood:  # the kernel sets every point's redo and counts them
            redo = np.empty((lf.size, sf.size), dtype=np.bool_)
            nredo = _k_cubic_lattice(sf, lf, *grid, good, self.rotation, dirs, redo)
        else:
            redo = np.ones((lf.size, sf.size), dtype=np.bool_)
            nredo = redo.size
        if nredo:
            ss, ll = np.broadcast_arrays(sf[None, :], lf[:, None])
            flat = dirs.reshape(-1, 3)
            self._polish(ss.reshape(-1), ll.reshape(-1), grid, 1e-3, flat, redo.reshape(-1))
        return dirs

    # ---- Jacobians ------------------------------------------------------------------------------

    def _camera_jacobian_flat(self, zc):
        n = zc.shape[0]
        smp = np.empty(n)
        lin = np.empty(n)
        jac = np.empty((n, 2, 3))
        _k_jac_camera(zc, self._q, self._code, smp, lin, jac)
        return smp, lin, jac

    def pixel_jacobian_camera(self, points_cam) -> np.ndarray:
        """∂(sample, line)/∂x_C (..., 2, 3) for camera-frame points, distortion and K included."""
        z, lead = _points(points_cam)
        return self._camera_jacobian_flat(z)[2].reshape(lead + (2, 3))

    def project_camera_frame_with_jacobian(self, points_cam):
        """(sample, line, ∂(sample, line)/∂x_C) of camera-frame vectors (N, 3): one kernel pass.

        The bundle adjustment (:mod:`spctool.stages.bundle`) projects the observations of every picture
        that shares these intrinsics at once, each with its own pose, through this call.
        """
        z, lead = _points(points_cam)
        smp, lin, jac = self._camera_jacobian_flat(z)
        return smp.reshape(lead), lin.reshape(lead), jac.reshape(lead + (2, 3))

    @property
    def intrinsics_key(self) -> tuple:
        """Everything but the pose that the projection depends on (model code and packed constants):
        two cameras with equal keys project camera-frame vectors identically."""
        return (self._code,) + self._q

    def project_with_jacobians(self, points) -> ProjectionJacobians:
        """Pixels and every pose/point Jacobian of body-fixed points (N, 3) in one pass."""
        p, lead = _points(points)
        zc = (p + self.scobj) @ self.rotation.T
        smp, lin, jc = self._camera_jacobian_flat(np.ascontiguousarray(zc))
        jp = jc @ self.rotation
        ja = jc @ skew(zc)
        return ProjectionJacobians(
            smp.reshape(lead),
            lin.reshape(lead),
            zc.reshape(lead + (3,)),
            jc.reshape(lead + (2, 3)),
            (-jp).reshape(lead + (2, 3)),
            ja.reshape(lead + (2, 3)),
            jp.reshape(lead + (2, 3)),
        )

    def jacobian_point(self, points) -> np.ndarray:
        """∂(sample, line)/∂P (..., 2, 3) for the landmark's body-fixed position P (km)."""
        p, lead = _points(points)
        zc = (p + self.scobj) @ self.rotation.T
        return (self._camera_jacobian_flat(zc)[2] @ self.rotation).reshape(lead + (2, 3))

    def jacobian_position(self, points) -> np.ndarray:
        """∂(sample, line)/∂(spacecraft position, body frame, km) (..., 2, 3); SCOBJ = −position."""
        return -self.jacobian_point(points)

    def jacobian_attitude(self, points) -> np.ndarray:
        """∂(sample, line)/∂δθ (..., 2, 3) for T⁺ = Rot(−δθ)·T (frames.apply_attitude_update): J_C·[x_C×]."""
        p, lead = _points(points)
        zc = (p + self.scobj) @ self.rotation.T
        return (self._camera_jacobian_flat(zc)[2] @ skew(zc)).reshape(lead + (2, 3))

    def jacobian_pose(self, points) -> np.ndarray:
        """[∂/∂position | ∂/∂δθ] (..., 2, 6): the pose-solve design matrix block per point."""
        j = self.project_with_jacobians(points)
        return np.concatenate([j.position, j.attitude], axis=-1)

    def jacobian_maplet(self, points, ux, uy, scale) -> np.ndarray:
        """J_xy = ∂(sample, line)/∂(x, y) (..., 2, 2) in px per maplet cell (spc-algorithms.md §7.3, §8.3).

        x is the offset along UX (J, axis 0), y along UY (I, axis 1); a cell is ``scale`` km, so
        ∂P/∂x = scale·UX and ∂P/∂y = scale·UY.  ``ux``, ``uy``, ``scale`` broadcast against the points.
        """
        p = np.asarray(points, dtype=np.float64)
        jp = self.jacobian_point(p)
        s = np.asarray(scale, dtype=np.float64)[..., None]
        cols = np.stack([s * np.asarray(ux, dtype=np.float64), s * np.asarray(uy, dtype=np.float64)], axis=-1)
        return jp @ cols
