"""Rotations and reference frames used by every geometry routine.

What is here (all vectorised over leading ``...`` axes):

* :func:`skew` — the cross-product matrix ``[v×]`` with ``skew(v) @ w == cross(v, w)``.
* :func:`rot_from_axis_angle` — SPC's ``ROT2MAT`` (spc-algorithms.md §10.2):
  ``R = cos θ·I + (1 − cos θ)·û ûᵀ + sin θ·[û×]``.
  **Sign convention:** this is the *active* right-handed rotation of a vector by θ about û,
  ``R·v = v cos θ + (û×v) sin θ + û(û·v)(1 − cos θ)``; equivalently ``R = exp([θû×])``.
* :func:`rot_from_rotvec` / :func:`rotvec_from_rot` — the same rotation parametrised by the rotation
  vector θû (exponential and logarithm maps), safe at θ → 0.
* :func:`apply_attitude_update` — SPC/L15 small-angle attitude update of a body→camera matrix,
  ``T⁺ = Rot(−δθ)·T⁻`` with the exact exponential map (spc-algorithms.md §10.3), which agrees to
  first order with L15 footnote 13, ``(I − [δθ×])·T⁻``.  With x_C = T·(P − t) this gives
  ``∂x_C/∂δθ = [x_C×]`` (erratum 3 of spc-algorithms.md §11).
* :func:`orthonormalize` — nearest proper rotation (polar decomposition by SVD).
* :func:`orient_frame` — SPC ``ORIENT``: maplet axes from a normal (spc-formats.md §1.2):
  UY = normalise(ẑ × UZ) (East), UX = UY × UZ (South); at the poles (|UZ_z| > 0.9998) UY starts
  from (0, 1, 0) and is orthogonalised against UZ.
* :func:`maplet_to_body` / :func:`body_to_maplet` — maplet-frame coordinates in cells
  (x along UX = J = NumPy axis 0, y along UY = I = axis 1, h along UZ) ↔ body-fixed km:
  ``P = V + SCALE·(x·UX + y·UY + h·UZ)`` (spc-formats.md §1.3; the map→body rotation has UX, UY, UZ
  as its **columns**, §1.2 and §8 item 7).
* illumination-angle helpers (incidence, emission, phase cosines) with clipped ``arccos``.
* :func:`unit_vector` — a direction normalised, refused in one line when not a finite non-zero 3-vector.
"""

from __future__ import annotations

import math

import numpy as np

from spctool.errors import SpcUsageError

__all__ = [
    "skew",
    "unskew",
    "normalize",
    "rot_from_axis_angle",
    "rodrigues",
    "rot_from_rotvec",
    "rotvec_from_rot",
    "apply_attitude_update",
    "orthonormalize",
    "orient_frame",
    "look_rotation",
    "map_to_body_matrix",
    "maplet_to_body",
    "body_to_maplet",
    "angle_between",
    "illumination_cosines",
    "POLE_LIMIT",
]

#: ORIENT switches to the polar branch when |UZ_z| exceeds this (spc-formats.md §1.2).
POLE_LIMIT = 0.9998


def _as3(v) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.shape[-1:] != (3,):
        raise ValueError(f"expected vectors with a last axis of length 3, got shape {a.shape}")
    return a


def skew(v) -> np.ndarray:
    """Cross-product matrix ``[v×]`` of shape (..., 3, 3): ``skew(v) @ w == np.cross(v, w)``."""
    v = _as3(v)
    out = np.zeros(v.shape + (3,), dtype=np.float64)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    out[..., 0, 1] = -z
    out[..., 0, 2] = y
    out[..., 1, 0] = z
    out[..., 1, 2] = -x
    out[..., 2, 0] = -y
    out[..., 2, 1] = x
    return out


def unskew(m) -> np.ndarray:
    """Vector of a (near) skew-symmetric matrix: the inverse of :func:`skew` (antisymmetric part)."""
    m = np.asarray(m, dtype=np.float64)
    return 0.5 * np.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], axis=-1
    )


def normalize(v) -> np.ndarray:
    """Unit vectors along ``v`` (..., 3).  Zero vectors give NaN (never a silent zero)."""
    v = _as3(v)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / n


def rot_from_axis_angle(axis, angle) -> np.ndarray:
    """SPC ``ROT2MAT``: ``cos θ·I + (1 − cos θ)·û ûᵀ + sin θ·[û×]`` (active, right-handed).

    ``axis`` (..., 3) is normalised here; ``angle`` (...) in radians broadcasts against it.
    Rotating x̂ by +90° about ẑ gives ŷ.
    """
    u = normalize(axis)
    th = np.asarray(angle, dtype=np.float64)
    c = np.cos(th)[..., None, None]
    s = np.sin(th)[..., None, None]
    eye = np.eye(3)
    return c * eye + (1.0 - c) * (u[..., :, None] * u[..., None, :]) + s * skew(u)


def rot_from_rotvec(rotvec) -> np.ndarray:
    """Exponential map ``exp([φ×])`` for rotation vectors φ = θ·û (..., 3); exact, stable at θ → 0.

    Equal to ``rot_from_axis_angle(φ/|φ|, |φ|)`` (the ``ROT2MAT`` convention).
    """
    phi = _as3(rotvec)
    if phi.shape == (3,):
        return _rot_from_one_rotvec(phi)
    th2 = np.sum(phi * phi, axis=-1)
    th = np.sqrt(th2)
    small = th < 1e-4
    safe = np.where(small, 1.0, th)
    # a = sin θ/θ, b = (1 − cos θ)/θ²; Taylor series below 1e-4 rad (error < 1e-17).
    a = np.where(small, 1.0 - th2 / 6.0 + th2 * th2 / 120.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - np.cos(safe)) / (safe * safe))
    k = skew(phi)
    return np.eye(3) + a[..., None, None] * k + b[..., None, None] * (k @ k)


def _rot_from_one_rotvec(phi) -> np.ndarray:
    """:func:`rot_from_rotvec` of one rotation vector (3,): the same numpy operations on numpy scalars,
    the branch taken instead of both computed and selected (no 0-d temporaries; 22 → ~8 µs, the Monte
    Carlo's attitude perturbation of every sample)."""
    th2 = np.sum(phi * phi, axis=-1)
    th = np.sqrt(th2)
    if th < 1e-4:
        a = 1.0 - th2 / 6.0 + th2 * th2 / 120.0
        b = 0.5 - th2 / 24.0 + th2 * th2 / 720.0
    else:
        a = np.sin(th) / th
        b = (1.0 - np.cos(th)) / (th * th)
    k = skew(phi)
    return np.eye(3) + a * k + b * (k @ k)


def rodrigues(rotvec) -> np.ndarray:
    """Alias of :func:`rot_from_rotvec` (Rodrigues' formula for a rotation vector)."""
    return rot_from_rotvec(rotvec)


def rotvec_from_rot(r) -> np.ndarray:
    """Logarithm map: the rotation vector φ (…, 3) with ``rot_from_rotvec(φ) == r``, |φ| ≤ π."""
    r = np.asarray(r, dtype=np.float64)
    cos_raw = 0.5 * (np.trace(r, axis1=-2, axis2=-1) - 1.0)
    w = unskew(r)  # = sin θ · û
    sin_th = np.linalg.norm(w, axis=-1)
    th = np.arctan2(sin_th, cos_raw)  # accurate everywhere, unlike arccos near 0 and π
    cos_th = np.clip(cos_raw, -1.0, 1.0)
    small = th < 1e-4
    near_pi = th > np.pi - 1e-3
    scale = np.where(small, 1.0 + th * th / 6.0, th / np.where(small | (sin_th == 0), 1.0, sin_th))
    out = w * scale[..., None]
    if np.any(near_pi):
        # Near π use the symmetric part: (R + I)/2 ≈ û ûᵀ (sign fixed by the antisymmetric part).
        sym = 0.5 * (r + np.swapaxes(r, -1, -2)) - cos_th[..., None, None] * np.eye(3)
        sym = sym / np.where(1.0 - cos_th == 0, 1.0, 1.0 - cos_th)[..., None, None]
        idx = np.argmax(np.diagonal(sym, axis1=-2, axis2=-1), axis=-1)
        col = np.take_along_axis(sym, idx[..., None, None].repeat(3, axis=-1), axis=-2)[..., 0, :]
        u = normalize(col)
        sgn = np.sign(np.sum(u * w, axis=-1))
        sgn = np.where(sgn == 0, 1.0, sgn)
        out = np.where(near_pi[..., None], (sgn * th)[..., None] * u, out)
    return out


def orthonormalize(r) -> np.ndarray:
    """Nearest proper rotation (det +1) to ``r`` (..., 3, 3) in the Frobenius norm (SVD polar factor)."""
    r = np.asarray(r, dtype=np.float64)
    u, _, vt = np.linalg.svd(r)
    d = np.sign(np.linalg.det(u @ vt))
    if r.ndim == 2:  # one matrix: a numpy scalar, no 0-d temporaries
        u = u.copy()
        u[:, 2] *= 1.0 if d == 0 else d
        return u @ vt
    d = np.where(d == 0, 1.0, d)
    u = u.copy()
    u[..., :, 2] *= d[..., None]
    return u @ vt


def apply_attitude_update(t_body_to_camera, dtheta, *, reorthonormalize: bool = True) -> np.ndarray:
    """Small-angle attitude update ``T⁺ = Rot(−δθ)·T⁻`` (spc-algorithms.md §10.3, L15 footnote 13).

    ``Rot`` is the exact exponential map (:func:`rot_from_rotvec`), so to first order
    ``T⁺ = (I − [δθ×])·T⁻``.  δθ (radians) is expressed in the **camera** frame, and camera-frame
    vectors change as ``x_C⁺ ≈ x_C + x_C × δθ``, i.e. ``∂x_C/∂δθ = [x_C×]``
    (spc-algorithms.md §11 erratum 3).  The result is re-orthonormalised unless told otherwise.
    """
    t = np.asarray(t_body_to_camera, dtype=np.float64)
    out = rot_from_rotvec(-_as3(dtheta)) @ t
    return orthonormalize(out) if reorthonormalize else out


def orient_frame(uz) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SPC ``ORIENT``: maplet axes (UX, UY, UZ) from a normal ``uz`` (..., 3), spc-formats.md §1.2.

    UZ = normalise(uz); UY = normalise(ẑ × UZ) (East); UX = UY × UZ (South).  Where |UZ_z| > 0.9998
    (the poles) UY starts from (0, 1, 0), is orthogonalised against UZ and normalised.  The triad is
    right-handed: UZ = UX × UY.
    """
    uz = normalize(uz)
    east = np.stack([-uz[..., 1], uz[..., 0], np.zeros_like(uz[..., 0])], axis=-1)  # ẑ × UZ
    polar = np.abs(uz[..., 2]) > POLE_LIMIT
    if np.any(polar):
        y0 = np.array([0.0, 1.0, 0.0])
        gs = y0 - np.sum(uz * y0, axis=-1, keepdims=True) * uz
        east = np.where(polar[..., None], gs, east)
    uy = normalize(east)
    ux = np.cross(uy, uz)
    return ux, uy, uz


def look_rotation(position, target, roll_deg: float = 0.0) -> np.ndarray:
    """Body→camera rotation (rows CX, CY, CZ) of a camera at ``position`` looking at ``target``.

    CZ = boresight; CX = normalise(ẑ × CZ) (x̂ × CZ when CZ ∥ ẑ), rotated by ``roll_deg`` about CZ;
    CY = CZ × CX, so CX × CY = CZ.
    """
    cz = np.asarray(target, float) - np.asarray(position, float)
    cz = cz / np.linalg.norm(cz)
    ref = np.array([0.0, 0.0, 1.0]) if abs(cz[2]) < 0.999 else np.array([1.0, 0.0, 0.0])
    cx = np.cross(ref, cz)
    cx /= np.linalg.norm(cx)
    cy = np.cross(cz, cx)
    a = math.radians(roll_deg)
    cx, cy = math.cos(a) * cx + math.sin(a) * cy, -math.sin(a) * cx + math.cos(a) * cy
    return np.vstack([cx, cy, cz])


def map_to_body_matrix(ux, uy, uz) -> np.ndarray:
    """Maplet→body rotation (..., 3, 3) with UX, UY, UZ as its **columns** (spc-formats.md §1.2, §8.7)."""
    return np.stack([_as3(ux), _as3(uy), _as3(uz)], axis=-1)


def maplet_to_body(points_xyz_cells, v, ux, uy, uz, scale) -> np.ndarray:
    """Body-fixed km of maplet coordinates ``(x, y, h)`` in cells: ``P = V + SCALE·(x·UX + y·UY + h·UZ)``.

    x runs along UX (= J, NumPy axis 0), y along UY (= I, axis 1), h along UZ (spc-formats.md §1.3).
    All arguments broadcast; ``points_xyz_cells`` is (..., 3).
    """
    p = _as3(points_xyz_cells)
    s = np.asarray(scale, dtype=np.float64)[..., None]
    return _as3(v) + s * (p[..., 0:1] * _as3(ux) + p[..., 1:2] * _as3(uy) + p[..., 2:3] * _as3(uz))


def body_to_maplet(points_body, v, ux, uy, uz, scale) -> np.ndarray:
    """Inverse of :func:`maplet_to_body`: ``(x, y, h) = [UX UY UZ]ᵀ·(P − V)/SCALE`` in cells (..., 3).

    Exact for an orthonormal triad (the SPC files hold triads orthonormal to ~1e-7).
    """
    d = (_as3(points_body) - _as3(v)) / np.asarray(scale, dtype=np.float64)[..., None]
    return np.stack(
        [np.sum(d * _as3(ux), axis=-1), np.sum(d * _as3(uy), axis=-1), np.sum(d * _as3(uz), axis=-1)], axis=-1
    )


def angle_between(a, b) -> np.ndarray:
    """Angle in radians between vectors ``a`` and ``b`` (..., 3), robust for tiny and near-π angles."""
    a = _as3(a)
    b = _as3(b)
    cr = np.linalg.norm(np.cross(a, b), axis=-1)
    dt = np.sum(a * b, axis=-1)
    return np.arctan2(cr, dt)


def illumination_cosines(points, normals, sun, spacecraft_position):
    """Cosines of incidence, emission and phase at body-fixed ``points`` (..., 3).

    ``normals`` are outward surface normals, ``sun`` the body→Sun unit vector (SUM ``SZ``; the Sun is
    taken at infinity) and ``spacecraft_position`` the body-frame spacecraft position (−SCOBJ).
    Returns ``(mu0, mu, cos_phase)``, each clipped to [−1, 1].
    """
    n = normalize(normals)
    s = normalize(sun)
    e = normalize(_as3(spacecraft_position) - _as3(points))  # surface → spacecraft
    mu0 = np.clip(np.sum(n * s, axis=-1), -1.0, 1.0)
    mu = np.clip(np.sum(n * e, axis=-1), -1.0, 1.0)
    cph = np.clip(np.sum(s * e, axis=-1), -1.0, 1.0)
    return mu0, mu, cph


def unit_vector(v, name: str = "vector") -> np.ndarray:
    """``v`` (3,) normalised; SpcUsageError if it is not a finite non-zero 3-vector."""
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,):
        raise SpcUsageError(f"{name} must be a 3-vector, got shape {np.shape(v)}")
    n = float(np.linalg.norm(a))
    if not (math.isfinite(n) and n > 0.0):
        raise SpcUsageError(f"{name} must be a finite non-zero vector, got {a.tolist()}")
    return a / n
