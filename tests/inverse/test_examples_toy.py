"""The E1 optimizer toy example runs at its full (tiny) size and reproduces the expected numbers."""

from __future__ import annotations

import numpy as np


def test_optimizer_toy_full_size(tmp_path, capsys, load_example):
    toy = load_example("optimizer_toy")
    res = toy.main(["--out", str(tmp_path), "--device", "cpu"])
    printed = capsys.readouterr().out
    assert (tmp_path / "optimizer_toy.png").stat().st_size > 10_000 and "device cpu" in printed
    assert set(res) == {"gd", "newton", "pg", "ig", "pg_lbfgsb"}
    for name, r in res.items():
        assert r["trajectory"].shape == (11, 2)
        assert f"{r['distance']:10.6f}" in printed, name
    # Closed forms after 10 iterations from (3, 3):
    #   PG:     x1 = 3 * 0.7^10, x2 = 3 * sqrt(0.7)^10      (y <- 0.7 y exactly)
    #   IG:     x1 = 3 * 0.7^10, x2 = 3 * 0.85^10           (dx2 = -0.3 x2^2 / (2 x2))
    #   Newton: x1 = 3 * (2/3)^10, x2 = 3 * (8/9)^10       (H^-1 g = (x1, x2/3), eta = 1/3)
    np.testing.assert_allclose(res["pg"]["x"], [3 * 0.7**10, 3 * 0.7**5], rtol=1e-12)
    np.testing.assert_allclose(res["ig"]["x"], [3 * 0.7**10, 3 * 0.85**10], rtol=1e-12)
    np.testing.assert_allclose(res["newton"]["x"], [3 * (2 / 3) ** 10, 3 * (8 / 9) ** 10], rtol=1e-12)
    # GD: x1 = 3 * 0.98^10; x2 by the recursion x2 <- x2 - 0.04 x2^3.
    x2 = 3.0
    for _ in range(10):
        x2 -= 0.04 * x2**3
    np.testing.assert_allclose(res["gd"]["x"], [3 * 0.98**10, x2], rtol=1e-12)
    # L-BFGS-B as local inverse reproduces the analytic PG.
    np.testing.assert_allclose(res["pg_lbfgsb"]["x"], res["pg"]["x"], atol=1e-5)
    d = {k: r["distance"] for k, r in res.items()}
    assert d["pg"] < d["ig"] < d["newton"] < d["gd"]
