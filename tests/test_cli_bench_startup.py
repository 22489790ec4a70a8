"""`tensortouch --help` builds the whole command tree without importing the heavy sides (torch, scipy,
zenoh, onnxruntime, ...): they are imported when a command runs. Checked in a fresh process; the time
it takes is a benchmark (`tensortouch bench cli`, docs/BENCHMARKS.md "CLI start-up"), not a test."""
import subprocess
import sys

from tensortouch.tools.bench.cli_bench import HEAVY, heavy_imports


def test_building_every_command_imports_no_heavy_module():
    assert heavy_imports() == []


def test_help_runs_and_lists_the_commands_without_heavy_imports():
    probe = ("import sys, contextlib, io\nfrom tensortouch.runtime.shells.cli import main\n"
             "out = io.StringIO()\nwith contextlib.redirect_stdout(out):\n    try:\n        main(['--help'])\n"
             "    except SystemExit as e:\n        assert e.code == 0, e.code\n"
             "assert 'train' in out.getvalue() and 'listen' in out.getvalue()\n"
             "print(' '.join(sorted({m.split('.')[0] for m in sys.modules})))\n")
    loaded = set(subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout.split())
    assert not loaded & set(HEAVY), sorted(loaded & set(HEAVY))


def test_a_subcommand_help_imports_only_its_own_side():
    """`tensortouch listen --help` needs no torch and no onnxruntime; `tensortouch bench fe --help` loads the
    FE bench's options (its module) and still no torch."""
    for argv in (["listen", "--help"], ["bench", "fe", "--help"], ["train", "all", "--help"]):
        probe = ("import sys\nfrom tensortouch.runtime.shells.cli import main\n"
                 f"try:\n    main({argv!r})\nexcept SystemExit:\n    pass\n"
                 "print('LOADED', ' '.join(sorted({m.split('.')[0] for m in sys.modules})))\n")
        out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
        loaded = set(out.split("LOADED", 1)[1].split())
        assert not loaded & {"torch", "onnxruntime", "sklearn", "matplotlib"}, (argv, sorted(loaded & set(HEAVY)))
