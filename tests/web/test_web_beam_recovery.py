"""The live page of a session through the Leica emScon tracker shows the beam breaks it
recovered (``session.beam_recoveries``)."""

from __future__ import annotations

import json
import os
import time

from service.processes import start_fake_cell

NET = os.environ.get("RECAL_TEST_NET", "127.0.0")


def test_live_page_counts_the_beam_recoveries(page, stack, web):
    # StartMeasurement 4 and 8 break the beam (poses 4 and 7, each measured again after the search)
    cell = start_fake_cell(
        stack.truth_path,
        f"{NET}.83",
        seed=8,
        extra=["--fault", "beam_break_at=4,8"],
        log_path=stack.home / "fake-cell-3.log",
    )
    try:
        model = json.loads(stack.nominal_path.read_text())
        doc = web.api(stack, "POST", "/cells", {"name": "beam breaks", "model": model, "devices": cell.ready})
        s = web.api(stack, "POST", f"/cells/{doc['id']}/sessions", {"kind": "pose", "count": 14})
        deadline = time.monotonic() + 60
        while (s := web.api(stack, "GET", f"/sessions/{s['id']}"))["state"] in ("planned", "running"):
            assert time.monotonic() < deadline, s
            time.sleep(0.2)
        assert s["state"] == "completed" and s["beam_recoveries"] == 2, s
        web.sign_in(page, stack)
        page.goto(f"{stack.url}/#/sessions/{s['id']}")
        page.wait_for_selector("#beam-recoveries")
        assert page.inner_text("#beam-recoveries").startswith("2: the beam broke and the tracker found the reflector")
        web.shot(page, "30-session-beam-recoveries")
    finally:
        cell.stop()
