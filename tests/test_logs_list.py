"""`logs list` names the trainee entered at a session's start beside the operator the
appliance profile names, and '-' for a session without one."""

from __future__ import annotations

from teaching_script import scripted_session

from appliance.cli import main
from appliance.records.ledger import Ledger


def test_logs_list_shows_the_trainee(tmp_path, capsys):
    ledger = tmp_path / "ledger.sqlite"
    scripted_session(ledger)                       # the badge reader types "Ada Lovelace"
    with Ledger(ledger) as second:                 # a session without teaching
        second.start_session("Dr Who", "case", "C-arm", t_wall=1.8e9, t_monotonic=0.0)
        second.end_session(t_wall=1.8e9 + 60)
    assert main(["logs", "list", "--ledger", str(ledger)]) == 0
    header, first, other = capsys.readouterr().out.splitlines()
    assert header.split()[3:5] == ["operator", "trainee"]
    assert first.split()[:5] == ["1", "2023-11-14T22:13:20.000Z", "trainee", "Ada", "Lovelace"]
    assert other.split()[:6] == ["2", "2027-01-15T08:00:00.000Z", "Dr", "Who", "-", "0.0"]
