"""Run every `tensortouch ...` command the README and docs/*.md show, in the active environment, and check
that each one works or fails cleanly: no traceback, no "invalid choice", and a missing extra is ONE
line naming it with the install form of this installation (`--form editable`: pip install -e '...[x]';
`--form wheel`: pip install 'tensortouch[x]'), exit 2.

    python .ci/documented_commands.py --form editable        # (.ci/base-install runs it in a base venv)

Commands come from code blocks and inline code. Commands run in a scratch folder with a private Zenoh
meeting point and a scratch copy of the calibration store and cache (no file may appear in the
checkout); long-running ones (run, listen, view, hand, benchmarks) are stopped after --timeout seconds,
which counts as working. Placeholders
(SESSION, ID, ...) stay as written: such a command may end with its one-line bad-input error (exit 2).
Optional parts in brackets and `...` are dropped.
"""
from __future__ import annotations

import argparse
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def documented_commands(root: Path = ROOT) -> list[str]:
    """`tensortouch ...` commands of README.md and docs/*.md (not docs/history): lines of code blocks
    (fenced or indented) and inline code."""
    found: list[str] = []
    for md in [root / "README.md", *sorted((root / "docs").glob("*.md"))]:
        fenced, pending = False, ""
        for raw in md.read_text(encoding="utf-8").splitlines():
            line = raw.strip()
            if line.startswith("```"):
                fenced, pending = not fenced, ""
                continue
            if not fenced:
                if raw.startswith("    ") and line.startswith("tensortouch "):     # an indented code block
                    found.append(clean(line))
                found += [clean(m) for m in re.findall(r"`(tensortouch [^`]+)`", raw)]   # inline code
                continue
            if pending:
                line = pending + " " + line
                pending = ""
            elif line.startswith("$ "):
                line = line[2:]
            if not line.startswith("tensortouch "):
                continue
            if line.endswith("\\"):
                pending = line[:-1].strip()
                continue
            found.append(clean(line))
    return sorted({c for c in found if c})


def clean(line: str) -> str:
    """The runnable part of a documented line: no comment, no [optional] parts, no `...`."""
    line = re.sub(r"\s#\s.*$", "", line)
    while re.search(r"\[[^\[\]]*\]", line):
        line = re.sub(r"\s*\[[^\[\]]*\]", "", line)
    line = line.replace("...", " ").replace("…", " ")
    if "[" in line or "]" in line or "|" in line or "<" in line:
        return ""
    return " ".join(line.split())


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def untracked(root: Path = ROOT) -> set[str]:
    """Files git does not know in the checkout (ignored ones left out); empty without git."""
    try:
        out = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=all"],
                             capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return set()
    return {line[3:] for line in out.splitlines() if line.startswith("??")}


def check(command: str, form: str, timeout: float, scratch: Path) -> str | None:
    """None when `command` works or fails cleanly, else what is wrong."""
    try:
        argv = shlex.split(command)
    except ValueError:
        return None
    exe = Path(sys.executable).with_name("tensortouch")
    env = dict(os.environ, TENSORTOUCH_ENDPOINT=f"tcp/127.0.0.1:{free_port()}",
               TENSORTOUCH_CALIBRATION=str(scratch / "calibration_store"), TENSORTOUCH_CACHE=str(scratch / "cache"),
               XDG_DATA_HOME=str(scratch / "data"), XDG_CACHE_HOME=str(scratch / "xdg-cache"))
    work = Path(tempfile.mkdtemp(dir=scratch))
    proc = subprocess.Popen([str(exe), *argv[1:]], cwd=work, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout)
        rc = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            out, err = proc.communicate()
        rc = None                                   # still running at the timeout: it works
    text = out + err
    if "Traceback (most recent call last)" in text:
        return f"traceback:\n{err[-1500:]}"
    bad_choice = re.search(r"invalid choice: '([^']*)'", err)
    if bad_choice and not re.fullmatch(r"[A-Z][A-Z0-9_]*", bad_choice.group(1)):   # not a documented METAVAR
        return f"unknown command: {err.strip().splitlines()[-1]}"
    if "extra" in err and "pip install" in err:
        lines = [x for x in err.splitlines() if x.strip()]
        if rc != 2 or len(lines) != 1:
            return f"the extra hint must be one line with exit 2 (rc {rc}):\n{err}"
        wanted = "pip install -e '" if form == "editable" else "pip install 'tensortouch["
        if wanted not in lines[0]:
            return f"the extra hint does not fit a {form} install: {lines[0]}"
    elif rc not in (None, 0, 1, 2, 130):
        return f"exit {rc}:\n{err[-1500:]}"
    return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--form", choices=("editable", "wheel"), required=True, help="how tensortouch is installed here")
    ap.add_argument("--timeout", type=float, default=6.0, help="seconds before a still-running command is stopped")
    ap.add_argument("--jobs", type=int, default=2, help="commands run at once")
    args = ap.parse_args(argv)
    import shutil

    from tensortouch.contracts.paths import calibration_dir

    commands = documented_commands()
    before = untracked()
    with tempfile.TemporaryDirectory(prefix="tt-doc-commands-") as scratch:
        # the calibration store and cache the commands may write: copies in the scratch folder
        # (a wheel's writable store may not exist yet: its shipped calibrations stay in the package)
        if calibration_dir().is_dir():
            shutil.copytree(calibration_dir(), Path(scratch) / "calibration_store")
        with ThreadPoolExecutor(max(1, args.jobs)) as pool:
            problems = list(pool.map(lambda c: (c, check(c, args.form, args.timeout, Path(scratch))), commands))
    bad = [(c, why) for c, why in problems if why]
    left = sorted(untracked() - before)
    if left:
        bad.append(("(all of them)", f"files left in the checkout: {left[:10]}"))
    for c, why in bad:
        print(f"FAIL {c}\n  {why}", file=sys.stderr)
    print(f"documented commands ({args.form} install): {len(commands) - len(bad)} of {len(commands)} work or fail "
          "cleanly")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
