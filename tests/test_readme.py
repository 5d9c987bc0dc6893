"""The README's library example runs as written and gives a sensible answer."""
import pathlib
import re

import numpy as np

README = pathlib.Path(__file__).resolve().parent.parent / "README.md"


def _python_blocks():
    return re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


def test_readme_library_example_runs():
    blocks = _python_blocks()
    assert blocks, "README has no python example"
    namespace: dict = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)
    estimate = namespace["estimate"]
    pose = np.asarray(estimate.pose)
    assert np.all(np.isfinite(pose))
    # Two moves of 0.5 m straight ahead with Table 1 noise: x within 0.2 m of 1.0.
    assert abs(pose[0] - 1.0) < 0.2, pose
    # Two trees seen twice: the best particle's map holds exactly two landmarks.
    assert int(np.sum(estimate.active)) == 2


def test_readme_names_the_two_commands():
    text = README.read_text()
    assert "jaxslam demo" in text
    assert "pytest" in text
