"""Numba kernels of the image-space template renderer (private; used by :mod:`spctool.stages.render`).

S16 "Future Retina development" correlates the photo against a rendered prediction of each maplet;
issue 17 asks for that render at maplet-space speed.  The kernels here do the per-window work around
the exact ray casting of :mod:`spctool.geometry._heightkernels` without NumPy temporaries:

* :func:`bin_subrays` — supersample bins: the mean radiance, coverage and shadow fraction of each
  pixel's n×n sub-rays (summed in the order NumPy's ``reshape(...).mean(axis=(1, 3))`` sums them, so
  the pixels are the same to the last bit; n < 8).
* :func:`shade_subrays` — the photometric law of :mod:`spctool.photometry` per sub-ray (times the
  albedo, 0 in shadow), on the fused kernel's (μ0, μ, cos α, albedo) without NumPy temporaries.
"""

from __future__ import annotations

import math

from numba import njit


@njit(cache=True, nogil=True)
def bin_subrays(r, hit, sh, surface, nss, rad, cov, shd, sid):
    """Pixel (a, s) of the (lines, samples) outputs from sub-rays m = ((a·nss + u)·width + s)·nss + v
    (line a, sub-line u, sample s, sub-sample v): rad = mean of r, cov / shd = fraction of ``hit`` /
    ``sh``, sid = ``surface`` of the pixel's first sub-ray.  Bit for bit NumPy's means for nss < 8
    (NumPy sums 8 or more terms pairwise; callers use NumPy there)."""
    nl, width = rad.shape
    k = nss * nss
    for a in range(nl):
        for s in range(width):
            m0 = ((a * nss) * width + s) * nss
            acc = 0.0
            nh = 0
            ns = 0
            for u in range(nss):
                row = 0.0  # NumPy: each sub-line's sum (sequential below 8 terms), then their sum
                for v in range(nss):
                    m = ((a * nss + u) * width + s) * nss + v
                    row += r[m]
                    nh += hit[m]
                    ns += sh[m]
                acc += row
            rad[a, s] = acc / k
            cov[a, s] = nh / k
            shd[a, s] = ns / k
            sid[a, s] = surface[m0]


#: photometric laws of :mod:`spctool.photometry` by code, for :func:`shade_subrays`
LAW_CODES = {"spc": 0, "mcewen": 1, "fixed": 2, "lambert": 3}


@njit(cache=True, nogil=True)
def shade_subrays(geom, sh, law, beta, alpha0, use_albedo, out):
    """The fused kernel's shading step per sub-ray: ``out[k]`` = R(μ0, μ, α)·albedo, 0 when shadowed.

    ``geom`` (N, 4) = (μ0, μ, cos α, albedo) per sub-ray; ``law`` a :data:`LAW_CODES` code, ``beta`` the
    constant β of ``fixed``, ``alpha0`` (deg) the limb-weight scale.  The arithmetic of
    :func:`spctool.photometry.reflectance` element by element (α = degrees(arccos(clip(cos α, ±1))),
    β = exp(−α/α0), dark where μ0 ≤ 0, μ ≤ 0 or μ0 + μ ≤ 1e-12; Lambert dark where μ0 ≤ 0 or μ ≤ 0),
    without its NumPy temporaries; the arccos and exp are skipped where the ray is dark or shadowed.
    """
    deg = 180.0 / math.pi
    for k in range(geom.shape[0]):
        if sh[k]:
            out[k] = 0.0
            continue
        mu0 = geom[k, 0]
        mu = geom[k, 1]
        if law == 3:
            r = 0.0 if (mu0 <= 0.0 or mu <= 0.0) else mu0
        elif mu0 <= 0.0 or mu <= 0.0 or mu0 + mu <= 1e-12:
            r = 0.0
        else:
            if law == 2:
                b = beta
            else:
                c = min(max(geom[k, 2], -1.0), 1.0)
                b = math.exp(-(math.acos(c) * deg) / alpha0)
            lommel = mu0 / (mu0 + mu)
            if law == 1:
                r = 2.0 * b * lommel + (1.0 - b) * mu0
            else:
                r = (1.0 - b) * mu0 + b * lommel
        out[k] = r * geom[k, 3] if use_albedo else r
