"""`tensortouch grasp`'s options: bad values are one line naming the option, exit 2."""
import pytest


@pytest.mark.parametrize("value", ["x", "1,2", "9", "nan", "-1"])
def test_a_bad_squeeze_is_one_line_naming_the_option(value, capsys):
    from tensortouch.runtime.shells.cli import main

    assert main(["grasp", "--squeeze-mm", value, "--trials", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--squeeze-mm" in err[0] and "0 to 5" in err[0]
