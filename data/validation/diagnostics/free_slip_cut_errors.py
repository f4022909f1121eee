"""Errors of a free-slip body's face fractions near a ball (the fluid inside, radius 0.5, faces normal to x within a
cell of the surface on an n^3 grid over [-0.6, 0.6]^3) against the exact cut: per sub-cut count m, the largest and rms
error of ``subface_cuts``' fraction (``python data/validation/diagnostics/free_slip_cut_errors.py``; prints
``[n, faces, m, max, rms, ...]``). At 1c8f227 the sub-cuts were planar (``free_slip_cut_errors_planar.txt``); since
8735b6a they are corrected for curvature (``curved_cut``, ``free_slip_cut_errors_curved.txt``)."""
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
from phisim.fluid.bodies import subface_cuts  # noqa: E402

F = torch.float64
R = 0.5


class Ball:
    """The fluid inside a ball about the origin."""

    def sdf(self, x, t):
        return R - x.norm(dim=-1)


def exact(points, h, k=4000):
    """Exact wetted fraction of the faces normal to x centred at ``points``: the plane x = x0 cuts the ball in a disc
    of radius rho, and the wetted area is the integral over y of the disc's chord in z within the face (midpoints)."""
    rho2 = (R ** 2 - points[:, 0] ** 2).clamp_min(0)
    t = (torch.arange(k, dtype=F) + 0.5) / k * h - h / 2
    out = []
    for sl in torch.arange(len(points)).split(500):
        p = points[sl]
        c = (rho2[sl, None] - (p[:, 1:2] + t[None]) ** 2).clamp_min(0).sqrt()
        lo = torch.maximum(p[:, 2:3] - h / 2, -c)
        hi = torch.minimum(p[:, 2:3] + h / 2, c)
        out.append((hi - lo).clamp_min(0).mean(1) / h)
    return torch.cat(out)


if __name__ == "__main__":
    torch.set_num_threads(1)
    body = Ball()
    for n in (16, 32, 64):
        h = 1.2 / n
        c = (torch.arange(n, dtype=F) + 0.5) * h - 0.6 + 0.0123 * h
        x = torch.stack(torch.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3)
        x[:, 0] -= h / 2
        faces = x[body.sdf(x, 0).abs() < h]
        ref = exact(faces, h)
        row = [n, len(faces)]
        for m in (1, 2, 4):
            e = subface_cuts(body, faces, 0.0, h, 0, m)[0] - ref
            row += [m, float(e.abs().max()), float(e.pow(2).mean().sqrt())]
        print(row, flush=True)
