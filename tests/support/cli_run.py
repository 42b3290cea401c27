"""``cellcal`` called in process, as the unit tests of the commands do."""
from __future__ import annotations

import contextlib
import io

from cellcal.cli.main import main


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of ``cellcal ARGV``."""
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def run_cli_captured(*argv: str) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of ``cellcal ARGV`` where pytest's capsys is not at hand
    (a module fixture's run)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(list(argv))
    return code, out.getvalue(), err.getvalue()


def one_message(err: str) -> str:
    """The one line a refused command prints on stderr (no traceback)."""
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("cellcal: ") and "Traceback" not in err, err
    return lines[0]


def refused(capsys, argv, code: int, needles) -> str:
    """``cellcal ARGV`` refused: exit status `code` (the argument parser's own refusals
    included), stdout empty, one line on stderr holding every needle, no traceback."""
    try:
        status = main([str(a) for a in argv])
    except SystemExit as stopped:  # the argument parser's own refusals, bounded numbers among them
        status = stopped.code
    assert status == code
    out, err = capsys.readouterr()
    assert "Traceback" not in err and err.count("\n") == 1, err
    for needle in needles:
        assert needle in err, err
    assert out == ""
    return err
