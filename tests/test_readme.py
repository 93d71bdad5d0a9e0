"""The README's step-API example runs as printed, and .ci/run runs the README's test command."""

import re
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def test_readme_step_api_example_runs():
    code = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)[0]
    scope = {}
    exec(compile(code, "README.md", "exec"), scope)
    x = scope["x"].numpy()
    assert x.shape == (scope["model"].vert_count, 3) and np.isfinite(x).all()
    # The head collider keeps every vertex out of the head: the ellipsoid's closed form in the head frame at the
    # last step (the example turns the head by 0.5 sin 2t about z). The roots lie on it, to float32.
    angle = -0.5 * np.sin(2.0 * 1.0)
    c, s = np.cos(angle), np.sin(angle)
    local = x @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T
    level = np.sum(((local - (0.0, 0.0, 1.6)) / (0.085, 0.1, 0.11)) ** 2, axis=1)
    assert level.min() > 1.0 - 1e-3, level.min()  # 1e-3 of the level: 0.05 mm below the surface


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / "README.md").read_text()
    test_command = re.findall(r"```bash\n(.*?)\n```", readme, re.S)[1].strip()
    assert test_command in (ROOT / ".ci" / "run").read_text()
