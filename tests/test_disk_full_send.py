"""An appliance started on a full disk queues its dose report to send once the ledger is
written back, and its send worker opens the queue then (a real 1 MiB tmpfs, as in
test_disk_full)."""

from __future__ import annotations

import dataclasses
import queue
from pathlib import Path

from test_disk_full import full_disk  # noqa: F401 - the fixture

from appliance.config.dicom import Destination, Dicom, Retry
from appliance.console.state import ConsoleEvent
from appliance.daemon.handoff import LatestValue, Recorded
from appliance.daemon.records_worker import RecordsWorker
from appliance.daemon.reload import ProfileKeeper
from appliance.daemon.send_worker import SendWorker
from appliance.records.deferred_ledger import DeferredLedger, open_ledger
from appliance.records.outbox import Outbox

REPO = Path(__file__).resolve().parents[1]


def test_a_session_begun_on_a_full_disk_queues_its_report_once_written(full_disk):  # noqa: F811
    keeper = ProfileKeeper(REPO / "configs/appliance-demo.yaml", data_dir=full_disk)
    cfg = keeper.current
    dicom = Dicom(send_at_shutdown_s=0, retry=Retry(poll_period_s=0.1),
                  destinations=[Destination(name="registry", ae_title="REG", host="127.0.0.1", port=1,
                                            objects="dose_reports")])
    keeper.current = dataclasses.replace(cfg, appliance=cfg.appliance.model_copy(update={"dicom": dicom}))
    ledger = open_ledger(full_disk / "ledger.sqlite")
    assert isinstance(ledger, DeferredLedger)
    events: queue.Queue = queue.Queue()
    clock = iter(range(100, 10_000)).__next__
    worker = RecordsWorker(ledger, keeper, None, lambda: float(clock()), events=events, shown=LatestValue(),
                           saves=LatestValue())
    sender = SendWorker(full_disk / "ledger.sqlite", keeper)
    worker.setup()
    assert worker.session_id is None and not sender._open()      # no ledger file yet: nothing to send from
    events.put(Recorded(ConsoleEvent(101.0, "fluoro_on", {"mode": "continuous"})))
    events.put(Recorded(ConsoleEvent(113.0, "fluoro_off", {"run": 1, "reason": "released", "start_t": 101.0,
                                                           "duration_s": 12.0, "air_kerma_mgy": 1.5, "dap_gy_cm2": 0.15,
                                                           "pulses": 0, "mode": "continuous", "zoom": 1},
                                     12.0, 1.5, 0.15, 12.0, 1.5, 0.15)))
    worker.step()
    (full_disk / "filler").unlink()
    worker.step()                                   # space returned: the session is written
    assert worker.session_id == 1
    worker.stop()
    worker.teardown()                               # the session ends: its report is queued
    ledger.close()
    with Outbox(full_disk / "ledger.sqlite", "dicom") as box:
        (pending,) = box.pending()
    assert (pending.label, pending.destination, pending.attempts) == ("dose report of session 1", "registry", 0)
    assert sender._open()
