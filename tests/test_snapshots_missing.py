"""The demo's list of pictures never taken (`Snapshotter.missing`), which the demo prints so an
absent picture is never taken for one that was looked at.

Ground truth: the demo's key moments in contact-sheet order, typed here by hand, the alarm's
reset (taken by its own rule, after the alarm) last.
"""

from __future__ import annotations

from appliance.daemon.snapshots import Snapshotter, key_moments

ORDER = ["first-live", "zoom-1", "zoom-2", "zoom-3", "zoom-4", "collimated", "inverted", "roll-plus-90",
         "roll-minus-90", "end-expiration", "end-inspiration", "breath-hold", "saved", "alarm", "last-image-hold",
         "tracking-lost", "alarm-reset"]


def test_with_nothing_seen_every_moment_is_missing_in_contact_sheet_order(tmp_path):
    snap = Snapshotter(tmp_path / "snapshots", key_moments())
    assert snap.missing() == ORDER
    assert snap.captions()["alarm-reset"] == "alarm reset"
    assert not (tmp_path / "snapshots").exists()          # nothing written for moments not seen


def test_a_moment_taken_leaves_the_list_and_the_rest_keep_their_order(tmp_path):
    snap = Snapshotter(tmp_path / "snapshots", key_moments())
    for name in ("zoom-3", "alarm-reset", "first-live"):
        snap.taken[name] = tmp_path / f"{name}.png"
    assert snap.missing() == [n for n in ORDER if n not in ("zoom-3", "alarm-reset", "first-live")]
