"""The README's Python snippet runs as written (twice: a second run must not fail on files the first
wrote), and its two copy-paste commands are the ones CI and users run."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def test_the_use_it_snippet_runs_and_reruns(tmp_path, monkeypatch, capsys):
    block = re.search(r"## Use it\n\n```python\n(.*?)```", README, re.S).group(1)
    (tmp_path / "models").symlink_to(ROOT / "models")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(block, "README.md", "exec"), namespace)
    assert 0 <= namespace["est"].in_domain.mean() <= 1 and (tmp_path / "build" / "obs" / "kkl_obs.c").exists()
    assert "Proposition 1 certificate" in capsys.readouterr().out
    rerun = "\n".join(line for line in block.splitlines() if "generate_c" in line)
    exec(compile(rerun, "README.md", "exec"), namespace)


def test_the_readme_commands_are_the_ones_ci_runs():
    commands = re.findall(r"```bash\n(python3 -m venv .*?)\n```", README)
    assert len(commands) == 2 and commands[0].endswith("kklcasadi demo")
    assert commands[1].endswith("ruff check . && python -m pytest -q")
    ci = (ROOT / ".ci" / "run").read_text()
    assert 'pip install -q -e ".[test]" && ruff check . && python -m pytest -q' in ci
