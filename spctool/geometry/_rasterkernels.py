"""Numba kernels of the image-space template renderer (private; used by :mod:`spctool.stages.render`).

S16 "Future Retina development" correlates the photo against a rendered prediction of each maplet;
issue 17 asks for that render at maplet-space speed.  The kernels here do the per-window work around
the exact ray casting of :mod:`spctool.geometry._heightkernels` without NumPy temporaries:

* :func:`bin_subrays` — supersample bins: the mean radiance, coverage and shadow fraction of each
  pixel's n×n sub-rays (summed in the order NumPy's ``reshape(...).mean(axis=(1, 3))`` sums them, so
  the pixels are the same to the last bit; n < 8).
"""

from __future__ import annotations

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
