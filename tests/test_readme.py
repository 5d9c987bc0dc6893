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


def test_readme_test_command_is_the_ci_command():
    """The README's test command runs pytest exactly as ``.ci/run`` does (same options), so a
    newcomer's run is the one CI judges."""
    ci = (README.parent / ".ci" / "run").read_text()
    ci_pytest = re.search(r"-m (pytest[^\n]*)", ci).group(1).strip()
    readme_pytest = re.findall(r"python -m (pytest[^\n`]*)", README.read_text())
    assert ci_pytest in [command.strip() for command in readme_pytest], (ci_pytest,
                                                                        readme_pytest)
