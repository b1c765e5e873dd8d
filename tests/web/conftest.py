"""Browser tests of the technician's web page: the real service (``recal serve``) and a
simulated cell (``recal fake-cell``) as processes, driven from Debian's Chromium through
Playwright (never ``playwright install``). Loopback addresses 127.0.0.80-127.0.0.89 are this
folder's (the UR ports are fixed per address). Screenshots land in ``tests/web/screenshots/``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from sqlmodel import Session

from calibration import robots
from calibration.simulate import perturbed
from service.files import save_model
from service.processes import free_port, start_fake_cell, start_service
from service.settings import Settings
from service.store import create_token, make_engine, migrate

# Loopback network of the simulated cells: RECAL_TEST_NET lets two test runs on one machine
# use disjoint addresses (the UR controller's ports are fixed per address).
NET = os.environ.get("RECAL_TEST_NET", "127.0.0")

CHROMIUM = os.environ.get("RECAL_CHROMIUM", "/usr/bin/chromium")
ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
SHOTS = Path(__file__).resolve().parent / "screenshots"
TABLET = {"width": 1024, "height": 768}  # a 10-inch tablet in landscape

BALLS = {"ball1": [0.06, 0.0, 0.04], "ball2": [-0.03, 0.052, 0.04], "ball3": [-0.03, -0.052, 0.04]}


def _browser_missing() -> str | None:
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "the browser tests need the playwright Python package (pip install playwright)"
    if not (Path(CHROMIUM).exists() or shutil.which(CHROMIUM)):
        return f"the browser tests need Chromium at {CHROMIUM} (apt-get install chromium)"
    return None


@pytest.fixture(scope="session")
def browser():
    reason = _browser_missing()
    if reason:
        pytest.skip(reason)
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        try:
            yield b
        finally:
            b.close()


@pytest.fixture
def page(browser):
    """A fresh tablet-sized page; JavaScript errors on it fail the test."""
    ctx = browser.new_context(viewport=TABLET, accept_downloads=True, device_scale_factor=1)
    pg = ctx.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.set_default_timeout(20_000)
    yield pg
    ctx.close()
    assert not errors, f"JavaScript errors on the page: {errors}"


def shot(page, name: str, *, full_page: bool = True) -> Path:
    """Save a screenshot for people to look at (tests/web/screenshots/NAME.png)."""
    SHOTS.mkdir(exist_ok=True)
    path = SHOTS / f"{name}.png"
    if full_page:  # the sticky header belongs at the top: scroll there, and make sure the page
        # stays there for two frames (a scroll the page started may still be running)
        page.wait_for_function("""() => new Promise((done) => {
            window.scrollTo({top: 0, behavior: 'instant'});
            requestAnimationFrame(() => requestAnimationFrame(() => done(window.scrollY === 0)));
        })""")
    page.screenshot(path=str(path), full_page=full_page)
    return path


SERVICE_ENV = {"RECAL_SETTLE_S": "0", "RECAL_RETRY_BACKOFF_S": "0.05"}


@dataclasses.dataclass
class Stack:
    url: str
    home: Path
    cell_ready: dict
    tokens: dict
    nominal_path: Path
    truth_path: Path
    cell_host: str
    crashed_cell_ready: dict  # the same cell after a crash bent link 3 (another simulated cell)
    service: object = None

    def crash_and_restart_service(self) -> None:
        """kill -9 the service (what a power loss does) and start it again on the same address."""
        port = int(self.url.rsplit(":", 1)[1])
        self.service.kill()
        self.service = start_service(self.home, port, env=SERVICE_ENV, log_path=self.home / "service.log")


def longer_link(model, k: int, by_m: float):
    """``model`` (``poe``) with the link after joint ``k`` (0-based) ``by_m`` longer: every later
    joint axis, and the flange, moved along the link's common normal."""
    j, nxt = model.joints[k], model.joints[k + 1]
    axis = j.axis / np.linalg.norm(j.axis)
    d = nxt.point - j.point
    d = d - axis * (d @ axis)
    d = d / np.linalg.norm(d) * by_m
    joints = tuple(dataclasses.replace(jj, point=jj.point + d) if i > k else jj for i, jj in enumerate(model.joints))
    home = np.array(model.home, dtype=float)
    home[:3] += d
    return dataclasses.replace(model, joints=joints, home=home)


@pytest.fixture(scope="module")
def stack(tmp_path_factory, browser):
    """A simulated UR10e cell (its robot protective-stops once, at the 6th move), the same
    robot after a crash lengthened its link 3 by 0.4 mm (a second simulated cell, 127.0.0.82),
    and the service on SQLite with a technician's and a viewer's token."""
    home = tmp_path_factory.mktemp("web")
    rng = np.random.default_rng(11)
    targets = {"smr": np.array([0.0, 0.0, 0.05]), **{k: np.array(v) for k, v in BALLS.items()}}
    nominal = dataclasses.replace(robots.nominal("ur10e"), targets=targets)
    truth = perturbed(nominal, rng, tool_length_m=0.0)
    truth = dataclasses.replace(
        truth,
        base=np.array([1.6, -0.5, 0.25, 0.002, -0.003, np.deg2rad(120.0)]),
        targets={k: v + rng.normal(0, 0.6e-3, 3) for k, v in targets.items()},
    )
    crashed = longer_link(truth, 2, 0.4e-3)  # the robot after a crash (the next calibration must see it)
    save_model(home / "nominal.json", nominal)
    save_model(home / "truth.json", truth)
    save_model(home / "crashed.json", crashed)
    engine = make_engine(Settings(home=home).effective_database_url)
    migrate(engine)
    tokens = {}
    with Session(engine) as db:
        for role in ("technician", "viewer"):
            tokens[role] = create_token(db, role=role, name=f"{role}-anna" if role == "technician" else "viewer-ben")[1]
    engine.dispose()
    host = f"{NET}.81"
    with ThreadPoolExecutor(2) as pool:  # both simulated cells start at once
        starting = [
            pool.submit(
                start_fake_cell,
                home / "truth.json",
                host,
                seed=5,
                time_scale=0.03,
                extra=["--fault", "protective_stop_at_move=6"],
                log_path=home / "fake-cell.log",
            ),
            pool.submit(
                start_fake_cell,
                home / "crashed.json",
                f"{NET}.82",
                seed=6,
                time_scale=0.03,
                log_path=home / "fake-cell-2.log",
            ),
        ]
    cells = [f.result() for f in starting if f.exception() is None]
    if len(cells) < len(starting):
        for c in cells:
            c.stop()
        raise next(f.exception() for f in starting if f.exception() is not None)
    cell, crashed_cell = cells
    stack = Stack("", home, cell.ready, tokens, home / "nominal.json", home / "truth.json", host, crashed_cell.ready)
    try:
        stack.service = start_service(home, free_port(), env=SERVICE_ENV, log_path=home / "service.log")
        stack.url = stack.service.ready["url"]
        yield stack
    finally:
        if stack.service is not None:
            stack.service.stop()
        cell.stop()
        crashed_cell.stop()


def sign_in(page, stack: Stack, role: str = "technician") -> None:
    sign_in_at(page, stack.url, stack.tokens[role])


def sign_in_at(page, url: str, token: str) -> None:
    """Sign in to the page of the service at ``url`` with ``token``."""
    page.goto(url + "/")
    page.fill("#token", token)
    page.click("#sign-in")
    page.wait_for_selector("#role")


def api(stack: Stack, method: str, path: str, body=None, role: str = "technician"):
    """The REST API directly (set-up and checks the page does not need)."""
    from service.client import Api

    return Api(stack.url, stack.tokens[role]).call(method, path, body)


def register_cell_by_api(stack: Stack, name: str) -> int:
    doc = json.loads(stack.nominal_path.read_text())
    return api(stack, "POST", "/cells", {"name": name, "model": doc, "devices": stack.cell_ready})["id"]


OVERFLOWING = """() => {
  const name = (el) => el.tagName.toLowerCase() + (el.id ? '#' + el.id : '')
    + (el.classList.length ? '.' + [...el.classList].join('.') : '') + ` "${(el.textContent || '').trim().slice(0, 40)}"`;
  const bad = [];
  for (const box of document.querySelectorAll('.card, .stat, .certificate')) {
    const r = box.getBoundingClientRect();
    if (!r.width) continue;
    for (const el of box.querySelectorAll('*')) {
      if (el.closest('svg') !== null && el.tagName.toLowerCase() !== 'svg') continue;
      const wrap = el.closest('.table-wrap');
      if (wrap && wrap !== el && box.contains(wrap)) continue;  // wide tables scroll in their own box
      const e = el.getBoundingClientRect();
      if (!e.width) continue;
      if (e.right > r.right + 1 || e.left < r.left - 1) bad.push(`${name(el)} sticks out of ${name(box)}`);
      else if (el.clientWidth && el.scrollWidth > el.clientWidth + 1 && getComputedStyle(el).overflowX === 'visible')
        bad.push(`the content of ${name(el)} overflows it (${el.scrollWidth} > ${el.clientWidth} px)`);
    }
  }
  return bad;
}"""


def overflowing(page) -> list[str]:
    """Elements on the page whose content sticks out of them or of their card (wide tables,
    which scroll sideways in their own box, apart)."""
    return page.evaluate(OVERFLOWING)


@contextlib.contextmanager
def service_with_technician(tmp_path: Path):
    """The real service on its embedded store in ``tmp_path``, with a technician's token:
    ``(url, token, engine, settings)``; stopped on exit."""
    settings = Settings(home=tmp_path)
    engine = make_engine(settings.effective_database_url)
    migrate(engine)
    with Session(engine) as db:
        token = create_token(db, role="technician", name="technician-anna")[1]
    service = start_service(tmp_path, free_port(), env={}, log_path=tmp_path / "service.log")
    try:
        yield service.ready["url"], token, engine, settings
    finally:
        service.stop()
        engine.dispose()


def store_finished_pose_session(engine, settings: Settings, cell_id: int, data, plan_info: dict) -> int:
    """A pose session of the cell that measured ``data`` (simulated rows, stored with the
    tracker's stated 20 um as a session stores them), finished as the session loop finishes one
    (no cell process needed). Returns its calibration's id."""
    from service import kinds, records
    from service.models import Cell, RunSession

    with Session(engine) as db:
        cell = db.get(Cell, cell_id)
        run = RunSession(
            cell_id=cell_id,
            kind="pose",
            state="running",
            planned=len(data),
            target="smr",
            created_by="technician-anna",
            plan=data.q.tolist(),
            plan_info=plan_info,
        )
        db.add(run)
        db.commit()
        db.refresh(run)
        db.add_all(records.measurement_rows(run.id, dataclasses.replace(data, sigma=np.full(len(data), 20e-6))))
        db.commit()
        kinds.finish_session(db, run, cell, settings)
        run.state = "completed"
        db.add(run)
        db.commit()
        return run.calibration_id


class Helpers:
    """What the tests use besides the page: the fixtures' helpers in one object (test modules
    cannot import the conftest under --import-mode=importlib)."""

    tablet = TABLET
    shot = staticmethod(shot)
    sign_in = staticmethod(sign_in)
    sign_in_at = staticmethod(sign_in_at)
    api = staticmethod(api)
    register_cell_by_api = staticmethod(register_cell_by_api)
    overflowing = staticmethod(overflowing)
    service_with_technician = staticmethod(service_with_technician)
    store_finished_pose_session = staticmethod(store_finished_pose_session)


@pytest.fixture
def web() -> Helpers:
    return Helpers()
