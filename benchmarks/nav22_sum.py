"""Summarise nav22_probe.py output: pooled RMS z, max |z|, median sigma per group and per
gyro-bias axis."""
import json
import sys

import numpy as np

rows = [json.loads(l) for f in sys.argv[1:] for l in open(f) if l.startswith("{")]
R2D = 180 / np.pi * 3600
print(f"{len(rows)} seeds, cpu {np.median([r['cpu_s'] for r in rows]):.1f} s median")
for k, f in (("gyro_bias", R2D), ("gyro_D", R2D * 9.80665), ("accel_bias", 1e6 / 9.80665)):
    e = np.array([r[k + "_err"] for r in rows])
    s = np.array([r[k + "_sig"] for r in rows])
    z = e / s
    print(f"{k}: RMS z {np.sqrt(np.nanmean(z**2)):.3f} max {np.nanmax(abs(z)):.2f} "
          f"med sigma {np.nanmedian(s) * f:.4g} RMS err {np.sqrt(np.nanmean(e**2)) * f:.4g}")
    if k == "gyro_bias":
        for i in range(3):
            print(f"   axis {'xyz'[i]}: RMS z {np.sqrt(np.mean(z[:, i]**2)):.3f}, "
                  f"med sigma {np.median(s[:, i]) * f:.4g}, RMS err {np.sqrt(np.mean(e[:, i]**2)) * f:.4g}")
c = np.array([r["cer_z"] for r in rows])
print(f"check_earth_rate RMS z {np.sqrt(np.mean(c**2)):.3f}")
print("axis noise mrad", np.round([r["axis_noise_mrad"] for r in rows], 4).tolist())
