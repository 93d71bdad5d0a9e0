"""The README's step-API example runs as printed, and .ci/run runs the README's test command."""

import re
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _head_levels(x):
    """The ellipsoid's closed form in the head frame at the example's last step (it turns the head by 0.5 sin 2t
    about z): below 1 inside."""
    angle = -0.5 * np.sin(2.0 * 1.0)
    c, s = np.cos(angle), np.sin(angle)
    local = x @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T
    return np.sum(((local - (0.0, 0.0, 1.6)) / (0.085, 0.1, 0.11)) ** 2, axis=1)


def test_readme_step_api_example_runs():
    readme = (ROOT / "README.md").read_text()
    code = re.findall(r"```python\n(.*?)```", readme, re.S)[0]
    scope = {}
    exec(compile(code, "README.md", "exec"), scope)
    x = scope["x"].numpy()
    assert x.shape == (scope["model"].vert_count, 3) and np.isfinite(x).all()
    # The head collider keeps every vertex out of the head. The roots lie on it, to float32: 1e-3 of the level is
    # 0.05 mm below the surface.
    assert _head_levels(x).min() > 1.0 - 1e-3, _head_levels(x).min()
    # Without it, as many vertices end inside as the README says (float32 sums in another order on another CPU may
    # move a few across the level)
    said = re.search(r"without `colliders` ends\s+with ([\d,]+) of its ([\d,]+) vertices", readme)
    scope = {}
    exec(compile(code.replace("colliders=colliders, ", ""), "README.md", "exec"), scope)
    x = scope["x"].numpy()
    inside = int((_head_levels(x) < 1.0 - 1e-3).sum())
    assert int(said.group(2).replace(",", "")) == len(x)
    assert abs(inside - int(said.group(1).replace(",", ""))) <= 0.05 * inside


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / "README.md").read_text()
    test_command = re.findall(r"```bash\n(.*?)\n```", readme, re.S)[1].strip()
    assert test_command in (ROOT / ".ci" / "run").read_text()
