"""Time a profile's grid correction (GridFieldModel.correct_image) against the Kang-Weiss and
colour-field correction of the same model (vigproc.core.correct.correct), interleaved, on a 6 MP
float32 frame (docs/benchmarks/colour.md). Run: python scripts/bench_grid_speed.py"""

import time, numpy as np
from vigproc.core.colour import ColourField
from vigproc.core.correct import correct
from vigproc.core.gridfield import GridField, GridFieldModel
W, H = 3000, 2000
x, y = np.meshgrid(np.linspace(-.5, .5, 33), np.linspace(-.5, .5, 22))
g = GridField(W, H, np.stack([-1.3 * (x*x + y*y), -(x*x + y*y), -.7 * (x*x + y*y)], -1))
m = GridFieldModel(W, H, p=(1 / 1800**2, 0, 1 / 1800**2), colour=ColourField(W, H, coeffs=[[.1, 0, 0], [0, 0, 0], [-.1, 0, 0]]), grid=g)
img = np.random.default_rng(0).uniform(.1, .9, (H, W, 3)).astype(np.float32)
correct(img, m); m.correct_image(img)
tk, tg = [], []
for _ in range(5):
    t = time.perf_counter(); correct(img, m); tk.append(time.perf_counter() - t)
    t = time.perf_counter(); m.correct_image(img); tg.append(time.perf_counter() - t)
print(f"Kang-Weiss + colour (correct): {np.median(tk):.2f} s; grid (correct_image): {np.median(tg):.2f} s; ratio {np.median(tg) / np.median(tk):.2f}")
