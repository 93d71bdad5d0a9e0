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


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / "README.md").read_text()
    test_command = re.findall(r"```bash\n(.*?)\n```", readme, re.S)[1].strip()
    assert test_command in (ROOT / ".ci" / "run").read_text()
