"""Write scenes/studio.exr: a small procedural lat-long environment map (256×128, linear RGB).

Row 0 is straight up (+z in psdr's z-up world), the middle row the horizon. A blue-to-white sky
gradient over a dim ground, with two soft rectangular "softboxes" that cast visible shadows.
Run: python scripts/make_studio_envmap.py [out.exr]
"""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from psdr_cli.support import fileio as io  # noqa: E402


def studio(width=256, height=128):
    theta = (np.arange(height) + 0.5) / height * np.pi          # polar angle from +z
    phi = (np.arange(width) + 0.5) / width * 2 * np.pi           # azimuth
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    elev = np.pi / 2 - th
    sky = np.where(elev[..., None] > 0,
                   np.array([0.35, 0.5, 0.9]) * (1 - np.sin(elev))[..., None] + np.array([0.9, 0.95, 1.0]) * np.sin(elev)[..., None],
                   np.array([0.12, 0.1, 0.08])[None, None, :] * np.ones_like(elev)[..., None])
    img = sky * 0.6
    for center_phi, center_elev, w, h, power in ((1.0, 0.6, 0.45, 0.3, 12.0), (3.8, 0.35, 0.6, 0.25, 5.0)):
        dphi = np.angle(np.exp(1j * (ph - center_phi)))
        box = np.exp(-(np.abs(dphi / w) ** 6 + np.abs((elev - center_elev) / h) ** 6))
        img = img + power * box[..., None] * np.array([1.0, 0.97, 0.92])
    return img.astype(np.float32)


if __name__ == "__main__":
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[1] / "scenes" / "studio.exr"
    io.write_rgb_exr(out, studio(), {"psdr.note": "procedural studio environment (scripts/make_studio_envmap.py)"})
    print(out)
