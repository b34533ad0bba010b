"""Line-scan (pushbroom) pictures: SPC's projection of a body-fixed point (spc-formats.md §2.4).

A SUM whose line 1 has ``L`` in column 14 describes a pushbroom image: each image line is exposed at its
own time.  Its ``LINE SCAN DATA`` block gives polynomial models, in the line number LN about
LN0 = CTR(2), of the spacecraft position and of the pointing (SPC's xV2IMGPL.f with xCommon.f SCOBJ,
POINTING and ROT2MAT; spctool reimplements the equations, no Fortran is copied):

* position: S(LN) = Rot(POL_AXIS, −POL·dl) · [ (R0₁ + R0₂·dl + R0₃·dl²) · Rot(TRJ_AXIS, τ) · U0 ],
  dl = LN − LN0, τ = TRJ₁·dl + TRJ₂·dl² + TRJ₃·dl³, with U0 and R0₁ the direction and length of the SUM's
  SCOBJ (xV2IMGPL overwrites the block's own U0 and R0₁);
* pointing: the rows CX, CY, CZ are first turned by the rotation vector Σₖ CAX(k,:)·dlᵏ (ROT2MAT, when
  LN ≠ LN0), then each rotated like the position, by τ about TRJ_AXIS and −POL·dl about POL_AXIS;
* the line of a point is where its focal-plane y (getmm, with the picture's ``DISTORT=`` model) crosses
  0: three secant steps from LN0 ± 50 about the current estimate; the sample is CTR(1) + K11·x there.
  (No legacy D terms and no other K-matrix terms: xV2IMGPL does not call MMPX for line-scan pictures.)

``Rot(a, θ)`` turns a vector by θ about the unit vector a, right-handed (SPICE VROTV; a zero axis
leaves the vector unchanged).
"""

from __future__ import annotations

import numpy as np

from spctool.errors import SpcUsageError
from spctool.geometry.frames import rot_from_rotvec

__all__ = ["rotate_about", "linescan_position", "linescan_pointing", "project_linescan"]


def rotate_about(v: np.ndarray, axis, theta) -> np.ndarray:
    """Rotate vectors ``v`` (..., 3) by ``theta`` (broadcast) about ``axis`` (3,), right-handed (VROTV)."""
    axis = np.asarray(axis, dtype=np.float64)
    n = np.linalg.norm(axis)
    v = np.asarray(v, dtype=np.float64)
    if n == 0.0:
        return v.copy()
    a = axis / n
    theta = np.asarray(theta, dtype=np.float64)[..., None]
    along = (v @ a)[..., None] * a
    perp = v - along
    return along + np.cos(theta) * perp + np.sin(theta) * np.cross(a, perp)


def _tau(ls, dl):
    return ls.trj[0] * dl + ls.trj[1] * dl**2 + ls.trj[2] * dl**3


def linescan_position(picture, line) -> np.ndarray:
    """SCOBJ at image line(s) ``line``: spacecraft → body centre, body frame (km)."""
    ls = picture.linescan
    dl = np.asarray(line, dtype=np.float64) - picture.ctr[1]
    r0 = np.linalg.norm(picture.scobj)
    u0 = picture.scobj / r0
    v = rotate_about(np.broadcast_to(u0, dl.shape + (3,)), ls.trj_axis, _tau(ls, dl))
    v = v * (r0 + ls.r0[1] * dl + ls.r0[2] * dl**2)[..., None]
    return rotate_about(v, ls.pol_axis, -ls.pol * dl)


def linescan_pointing(picture, line) -> np.ndarray:
    """Body → camera rotation(s) (..., 3, 3) at image line(s) ``line`` (rows WX, WY, WZ)."""
    ls = picture.linescan
    dl = np.asarray(line, dtype=np.float64) - picture.ctr[1]
    cmat = np.broadcast_to(picture.rotation, dl.shape + (3, 3)).copy()
    if len(ls.cax):
        powers = dl[..., None] ** np.arange(1, len(ls.cax) + 1)
        vec = powers @ ls.cax
        cmat = rot_from_rotvec(vec) @ cmat  # ROT2MAT (identity where dl = 0)
    tau = _tau(ls, dl)[..., None]
    cmat = rotate_about(cmat, ls.trj_axis, tau)
    return rotate_about(cmat, ls.pol_axis, (-ls.pol * dl)[..., None])


def project_linescan(picture, points, settings=None):
    """(sample, line, inside) of body-fixed ``points`` (..., 3) in a line-scan ``picture``, as xV2IMGPL.

    ``settings`` (INIT_LITHOS) supplies the ``DISTORT=`` model of the picture (getmm), if any.
    """
    from spctool.geometry.camera import Camera

    if picture.linescan is None:
        raise SpcUsageError(f"picture {picture.name} is not a line-scan picture (no LINE SCAN DATA)")
    model, coef = "NONE", np.zeros(0)
    if settings is not None:
        dm = settings.distortion_for(picture.name)
        from spctool.geometry.camera import MODELS

        if dm is not None and dm.model in MODELS and dm.model != "NONE":
            model, coef = dm.model, dm.coefficients
    focal = Camera(
        mmfl=picture.mmfl,
        ctr=picture.ctr,
        kmatrix=np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),  # identity K: focal_to_pixel gives mm + CTR
        rotation=np.eye(3),
        scobj=np.zeros(3),
        npx=picture.npx,
        nln=picture.nln,
        model=model,
        coefficients=coef,
        name=picture.name,
    )
    pts = np.asarray(points, dtype=np.float64)
    lead = pts.shape[:-1]
    pts = pts.reshape(-1, 3)

    def mm_at(line):
        u = linescan_position(picture, line) + pts
        w = linescan_pointing(picture, line)
        z = np.einsum("nij,nj->ni", w, u)
        with np.errstate(divide="ignore", invalid="ignore"):
            s, ln = focal.focal_to_pixel(z[:, 0] / z[:, 2], z[:, 1] / z[:, 2])
        return s - picture.ctr[0], ln - picture.ctr[1]

    z2 = np.full(len(pts), picture.ctr[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        for _ in range(3):
            x0, x1 = z2 - 50.0, z2 + 50.0
            y0, y1 = mm_at(x0)[1], mm_at(x1)[1]
            z2 = (x0 * y1 - x1 * y0) / (y1 - y0)
        xmm = mm_at(z2)[0]
    sample = picture.ctr[0] + picture.kmatrix[0, 0] * xmm
    line = z2
    inside = (sample >= 1) & (sample <= picture.npx) & (line >= 1) & (line <= picture.nln)
    return sample.reshape(lead), line.reshape(lead), inside.reshape(lead)
