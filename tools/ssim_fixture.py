#!/usr/bin/env python3
"""Writes tests/fixtures/ssim_skimage.json: SSIM values and gradients computed independently by
scikit-image (structural_similarity with gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1, i.e. the 11x11 window of Wang et al. 2004 with
C1 = 0.01^2, C2 = 0.03^2) for two small deterministic grey images.

scikit-image filters with reflect padding and averages only the interior (5 px from the
border), so the test compares the SSIM map in the interior and the gradient in the deep interior
(10 px from the border), where padding plays no part.

The gradient is d mean(S) / dx by central differences (step 1e-6) of scikit-image's own SSIM map.
(Its `gradient=True` output, Avanaki's formula, does not match differences of its own map: at
pixel (10, 10) of these images it gives 1.33e-3 where the differences give -3.97e-5, so it is not
used.)

Run once: python3 -m venv v && v/bin/pip install scikit-image && v/bin/python tools/ssim_fixture.py
"""
import json
import pathlib

import numpy as np
import skimage
from skimage.metrics import structural_similarity

rng = np.random.default_rng(20261121)
h, w = 30, 34
yy, xx = np.mgrid[0:h, 0:w]
# Smooth structure plus noise, so that the SSIM is neither ~1 nor ~0.
x = 0.5 + 0.3 * np.sin(xx / 4.0) * np.cos(yy / 5.0) + 0.05 * rng.standard_normal((h, w))
y = 0.45 + 0.25 * np.sin(xx / 4.5 + 0.3) * np.cos(yy / 5.0) + 0.08 * rng.standard_normal((h, w))
x = np.clip(x, 0, 1)
y = np.clip(y, 0, 1)
kw = dict(gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0, full=True)
mssim, smap = structural_similarity(x, y, **kw)
grad = np.zeros((h, w))
eps = 1e-6
for r in range(10, h - 10):
    for c in range(10, w - 10):
        xp = x.copy()
        xm = x.copy()
        xp[r, c] += eps
        xm[r, c] -= eps
        sp = structural_similarity(xp, y, **kw)[1].mean()
        sm = structural_similarity(xm, y, **kw)[1].mean()
        grad[r, c] = (sp - sm) / (2 * eps)
out = {
    "source": f"scikit-image {skimage.__version__}, tools/ssim_fixture.py",
    "width": w,
    "height": h,
    "x": x.ravel().tolist(),
    "y": y.ravel().tolist(),
    "ssim_map": smap.ravel().tolist(),
    "mssim_interior": float(mssim),
    # d mean(S over all pixels) / dx, in the deep interior only (zero elsewhere)
    "grad_mean_ssim": grad.ravel().tolist(),
}
path = pathlib.Path(__file__).resolve().parent.parent / "tests" / "fixtures" / "ssim_skimage.json"
path.write_text(json.dumps(out))
print(f"wrote {path}: mssim {mssim:.6f}")
