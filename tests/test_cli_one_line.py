"""An argument mistake is one whole line (cli.OneLineParser): the command that refused, what is
wrong, where the usage is, and the line's end, so the shell's prompt or the next message starts
on a line of its own; exit status 2.

Ground truth: the line's parts as the parser's contract states them, typed here.
"""

from __future__ import annotations

import pytest

from appliance.cli import main


@pytest.mark.parametrize("argv, prefix, command", [
    (["render", "--size", "0"], "fluorosim render: argument --size: ", "fluorosim render"),
    (["frobnicate"], "fluorosim: argument COMMAND: invalid choice: 'frobnicate'", "fluorosim"),
    # A duration that is not one: the bench would end at once (NaN), run forever (inf) or fail
    # later with a traceback (a negative one).
    *[(["bench", "e2e", "--minutes", m], f"fluorosim bench e2e: argument --minutes: '{m}': give a finite number "
       "above 0", "fluorosim bench e2e") for m in ("nan", "inf", "-1", "0", "ten")],
    *[(["bench", "e2e", "--still", t], f"fluorosim bench e2e: argument --still: '{t}': give a finite number "
       "of 0 or more", "fluorosim bench e2e") for t in ("nan", "-3")],
    (["bench", "e2e", "--ct", "abdomen"], "fluorosim bench e2e: argument --ct: invalid choice: 'abdomen'",
     "fluorosim bench e2e"),
])
def test_an_argument_mistake_is_one_whole_line(argv, prefix, command, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2
    assert err.startswith(prefix), err
    assert err.endswith(f" (see '{command} --help')\n") and err.count("\n") == 1, repr(err)
