"""Reference SSIM for matloc-core's unit test (scikit-image, standard Wang et al. settings).

Run: pip install scikit-image numpy && python bench/reference/ssim_reference.py
The pattern must stay identical to `pattern()` in matloc-core/src/metrics.rs (f32 arithmetic).
"""
import numpy as np
from skimage.metrics import structural_similarity


def pattern(w, h, phase):
    y, x = np.mgrid[0:h, 0:w]
    xf = x.astype(np.float32)
    yf = y.astype(np.float32)
    v = (np.float32(0.5)
         + np.float32(0.3) * (np.sin(xf * np.float32(0.37) + np.float32(phase)) * np.cos(yf * np.float32(0.23)))
         + np.float32(0.15) * (((x * 7 + y * 13) % 17).astype(np.float32) / np.float32(17.0) - np.float32(0.5)))
    return v.astype(np.float32).astype(np.float64)


a = pattern(48, 40, 0.0)
b = pattern(48, 40, 0.4)
s = structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
                          use_sample_covariance=False, data_range=1.0)
print(f"{s:.12f}")
