"""The fractions of the carried free-slip outer sphere's faces (``tests/phisim/fluid/test_moving_bodies_order_3d.py
--free-slip`` at t = 0.05) against the exact cut, per velocity component: rms and largest error and where the largest
lies; then the sub-faces of component 0's worst face whose corrected cut errs (the 64^3 outlier of docs/VALIDATION.md:
a sub-face cut off at a corner). ``python data/validation/diagnostics/free_slip_cut_outlier.py 64``
(``free_slip_cut_outlier_64.txt``)."""
import itertools
import sys
from pathlib import Path

import torch

root = Path(__file__).resolve().parents[3]
for p in (root, root / "tests" / "phisim" / "fluid", Path(__file__).resolve().parent):
    sys.path.insert(0, str(p))

import free_slip_cut_errors as cuts  # noqa: E402
import test_moving_bodies_order_3d as study_3d  # noqa: E402

from phisim import Grid  # noqa: E402
from phisim.fluid.bodies import FREE_SLIP_SUBFACES, curved_cut, face_normal, planar_cut, sdf_gradient, subface_cuts  # noqa: E402,E501

F = torch.float64

if __name__ == "__main__":
    torch.set_num_threads(1)
    n, t = int(sys.argv[1]), 0.05
    grid = Grid((n, n, n), bounds=[(-study_3d.HALF_FREE_SLIP, study_3d.HALF_FREE_SLIP)] * 3)
    h = grid.dx[0]
    outer = study_3d.bodies(True)[1]
    c = study_3d.centre(t)
    cuts.R = study_3d.SC.R2
    m = FREE_SLIP_SUBFACES[3]
    worst = None
    for i in range(3):
        x = grid.face_centers(i, F).reshape(-1, 3)
        faces = x[outer.sdf(x, t).abs() < h]
        perm = [i] + [a for a in range(3) if a != i]  # the exact cut takes faces normal to its first axis
        ref = cuts.exact((faces - c)[:, perm], h)
        theta = subface_cuts(outer, faces, t, h, i, m)[0]
        e = (theta - ref).abs()
        k = int(e.argmax())
        r = (faces[k] - c).norm()
        print(f"component {i}: {len(faces)} faces, fraction error rms {float(e.pow(2).mean().sqrt()):.2e} largest "
              f"{float(e.max()):.2e} (theta {float(theta[k]):.4f}, {float((cuts.R - r) / h):.3f} cells inside the "
              f"fluid, normal {float(((faces[k] - c) / r)[i].abs()):.3f} along the face's axis)")
        if i == 0:
            worst = faces[k]
    s = h / m
    for oa, ob in itertools.product([((j + 0.5) / m - 0.5) * h for j in range(m)], repeat=2):
        xs = (worst + torch.tensor([0.0, oa, ob], dtype=F))[None]
        g = face_normal(sdf_gradient(outer, xs, t, 1e-3 * h), 0)
        planar = float(planar_cut(outer.sdf(xs, t), g, s)[0])
        curved = float(curved_cut(outer, xs, t, g, s, 0)[0])
        exact = float(cuts.exact(xs - c, s))
        if abs(curved - exact) > 1e-4:
            print(f"sub-face at ({oa / h:+.3f}, {ob / h:+.3f}) cells: planar {planar:.5f} corrected {curved:.5f} "
                  f"exact {exact:.5f}")
