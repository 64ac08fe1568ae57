"""The README's commands and .ci/run stay in step."""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _ci_test_command() -> str:
    lines = [ln.strip() for ln in (ROOT / ".ci" / "run").read_text().splitlines()]
    cmds = [ln for ln in lines if ln.startswith("python -m pytest")]
    assert len(cmds) == 1, cmds
    return cmds[0]


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / "README.md").read_text()
    cmd = _ci_test_command()
    assert f'pip install -e ".[test]" && {cmd}' in readme
    assert '-e ".[test]"' in (ROOT / ".ci" / "run").read_text()


def test_readme_main_job_command():
    readme = (ROOT / "README.md").read_text()
    assert "pip install -e . && fsjax tour --out tour_out" in readme


def test_ci_runs_the_main_job_on_a_bare_install():
    ci = (ROOT / ".ci" / "run").read_text()
    lines = [ln.strip() for ln in ci.splitlines() if not ln.strip().startswith("#")]
    assert ".ci-bare/bin/python -m pip install --quiet -e ." in lines  # no extras
    tour = [ln for ln in lines if "fsjax tour --quick" in ln and not ln.startswith("echo")]
    assert len(tour) == 1 and ".ci-bare/bin/fsjax" in tour[0]
    # it runs before the test extras are installed anywhere
    assert ci.index("fsjax tour --quick") < ci.index('-e ".[test]"')
