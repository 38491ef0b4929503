"""The derivation report, checked as a person would see it: rendered in a real browser."""

from __future__ import annotations

import base64
import contextlib
import dataclasses
import fcntl
import functools
import json
import os
import re
import select
import shutil
import subprocess
import sys
import time
from html.entities import html5
from pathlib import Path
from typing import IO, Any, cast
from xml.etree import ElementTree

import pytest
import sympy as sp

from tvopt_codegen import symbolic as sx
from tvopt_codegen.cli import main
from tvopt_codegen.derivation import derive
from tvopt_codegen.lowering.ir import lower
from tvopt_codegen.report import HEADINGS, render_report
from tvopt_codegen.report.entries import as_sympy
from tvopt_codegen.report.sections import _shown
from tvopt_codegen.spec import load_spec

from .conftest import EXAMPLES, ROOT, derivation, kernels, shared, write_spec

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
BROWSER_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
    # Any attempt to reach a host fails loudly instead of leaving the machine.
    "--host-resolver-rules=MAP * ~NOTFOUND",
    "--enable-logging=stderr",
    "--v=0",
]
GOLDEN = ROOT / "tests" / "golden"
#: The car whose det R holds a name and a cosine side by side, derived once (conftest's)
#: for both tests that read its report.
CAR = str(ROOT / "tests" / "specs" / "kinematic_car.toml")


def _latex(expr: object) -> str:
    """SymPy's LaTeX of ``expr`` (of either engine), as the report writes it.

    A sum's terms and a product's factors in the order of their arguments (SymPy's
    ``order="none"``), which is the same from either engine; a thin space between factors.
    """
    return str(sp.latex(as_sympy(expr), order="none", mul_symbol=r"\,"))


def _fixed(name: str):  # noqa: ANN202 - a Derivation with timings that do not vary
    d = derivation(name)
    return dataclasses.replace(d, timings=tuple((stage, 0.0) for stage, _ in d.timings))


@functools.cache
def _html(name: str) -> str:
    """An example's HTML report, rendered once for the browser and the self-contained test."""
    return render_report(derivation(name), kernels(name), formats=("html",))[f"{name}_report.html"]


#: Moves the DevTools pipe's ends to descriptors 3 and 4, where the browser reads and
#: writes them, and starts the browser in their place.
TRAMPOLINE = """import os, sys
os.dup2(int(sys.argv[1]), 3)
os.dup2(int(sys.argv[2]), 4)
os.execv(sys.argv[3], sys.argv[3:])
"""


class _DevTools:
    """One headless Chromium, driven over its DevTools pipe (fds 3 and 4, NUL-ended JSON).

    Each page is a tab of this one browser: a launch was 0.75 s of CPU for a few hundredths
    of painting, nine launches per run. ``timeout`` bounds the whole session.
    """

    def __init__(self, command: list[str], stderr: IO[bytes], timeout: float) -> None:
        to_browser, self._write = os.pipe()
        self._read, from_browser = os.pipe()
        # The browser's ends above 4 (pytest's captures hold low descriptors, and a pipe
        # end at 3 or 4 would be overwritten by the other's move), moved to 3 and 4 by
        # an interpreter that then becomes the browser.
        ends = [fcntl.fcntl(end, fcntl.F_DUPFD_CLOEXEC, 5) for end in (to_browser, from_browser)]
        for end in (to_browser, from_browser):
            os.close(end)
        self._deadline = time.monotonic() + timeout
        self.process = subprocess.Popen(
            [sys.executable, "-S", "-c", TRAMPOLINE, *map(str, ends), *command],
            pass_fds=ends,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=stderr,
        )
        for end in ends:
            os.close(end)
        self._buffer = b""
        self._sent = 0
        self.events: list[dict[str, Any]] = []

    def _message(self) -> dict[str, Any]:
        while b"\0" not in self._buffer:
            left = self._deadline - time.monotonic()
            if left <= 0 or not select.select([self._read], [], [], left)[0]:
                raise TimeoutError("the browser did not answer in time")
            chunk = os.read(self._read, 1 << 20)
            if not chunk:
                raise EOFError("the browser closed its DevTools pipe")
            self._buffer += chunk
        message, _, self._buffer = self._buffer.partition(b"\0")
        return cast(dict[str, Any], json.loads(message))

    def call(self, method: str, session: str | None = None, **params: Any) -> dict[str, Any]:
        """Send a command (to a tab's ``session``) and return its result; events are kept."""
        self._sent += 1
        message: dict[str, Any] = {"id": self._sent, "method": method, "params": params}
        if session is not None:
            message["sessionId"] = session
        os.write(self._write, json.dumps(message).encode() + b"\0")
        while True:
            answer = self._message()
            if answer.get("id") == self._sent:
                assert "error" not in answer, (method, answer["error"])
                return cast(dict[str, Any], answer["result"])
            self.events.append(answer)

    def wait_for(self, method: str, session: str) -> None:
        """Read until the tab's event ``method`` has come."""
        while not any(
            e.get("method") == method and e.get("sessionId") == session for e in self.events
        ):
            self.events.append(self._message())

    def close(self) -> int:
        """Close the browser; its exit status."""
        with contextlib.suppress(EOFError):  # it may end before it answers
            self.call("Browser.close")
        code = self.process.wait(timeout=max(1.0, self._deadline - time.monotonic()))
        os.close(self._write)
        os.close(self._read)
        return code

    def kill(self) -> None:
        """End the browser if it still runs (a failed session)."""
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait()


#: What a page says that the tests read as a fault: its console, an uncaught exception,
#: and the browser's log of it (a resource that failed to load: ``net::ERR_...``).
SAID = ("Runtime.consoleAPICalled", "Runtime.exceptionThrown", "Log.entryAdded")


def _paint(browser: _DevTools, page: Path, here: Path) -> None:
    """``page`` in a new tab of ``browser``, painted at 1200 x 3000 after its load event:
    its screenshot, its DOM and what it said (as ``--screenshot`` and ``--dump-dom``)."""
    target = browser.call("Target.createTarget", url="about:blank")["targetId"]
    session = browser.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
    for domain in ("Page", "Runtime", "Log"):
        browser.call(f"{domain}.enable", session)
    # The size --window-size gives --screenshot (a tab's own viewport is the window's
    # less its frame): the same PNG, byte for byte.
    browser.call(
        "Emulation.setDeviceMetricsOverride",
        session,
        width=1200,
        height=3000,
        deviceScaleFactor=1,
        mobile=False,
    )
    browser.call("Page.navigate", session, url=page.as_uri())
    browser.wait_for("Page.loadEventFired", session)
    dom = browser.call(
        "Runtime.evaluate",
        session,
        expression="document.documentElement.outerHTML",
        returnByValue=True,
    )
    (here / "dom.html").write_text(dom["result"]["value"], encoding="utf-8")
    shot = browser.call("Page.captureScreenshot", session, format="png")
    (here / "shot.png").write_bytes(base64.b64decode(shot["data"]))
    browser.call("Target.closeTarget", targetId=target)
    ours = [e for e in browser.events if e.get("sessionId") == session]
    (here / "said.json").write_text(json.dumps([e for e in ours if e.get("method") in SAID]))
    browser.events = [e for e in browser.events if e.get("sessionId") != session]


#: The car's report with a script that measures its matrices' brackets and the gap after
#: "wheelbase" in det R, and writes what it found into the page.
PROBE = """<pre id="probe"></pre><script>
const out = [];
for (const t of document.querySelectorAll('mtable.matrix')) {
  const s = getComputedStyle(t), r = t.getBoundingClientRect();
  out.push(['matrix', parseFloat(s.borderLeftWidth) > 0 && parseFloat(s.borderRightWidth) > 0,
            r.height]);
}
for (const mi of document.querySelectorAll('mi')) {
  if (mi.textContent !== 'wheelbase') continue;
  const next = mi.nextElementSibling;
  if (!next || next.tagName.toLowerCase() !== 'mo' || !next.nextElementSibling) continue;
  const a = mi.getBoundingClientRect(), b = next.nextElementSibling.getBoundingClientRect();
  out.push(['gap', b.left - a.right]);
}
document.getElementById('probe').textContent = JSON.stringify(out);
</script></body>"""
#: The probed car's folder among the painted pages (no example's name).
CAR_PROBE = "kinematic_car_probe"


def _paint_every_example(folder: Path) -> None:
    """Each example's HTML report, and the probed car's, painted and its DOM read.

    One browser for all of them (a tab each): each page's folder gets its screenshot,
    its DOM and what it said; the folder gets the browser's log (stderr) and its exit
    status.
    """
    assert CHROMIUM is not None
    pages = {name: _html(name) for name in EXAMPLES}
    car = render_report(derivation(CAR), kernels(CAR), formats=("html",))
    pages[CAR_PROBE] = car["kinematic_car_report.html"].replace("</body>", PROBE)
    with (folder / "stderr").open("wb") as log:
        browser = _DevTools(
            [CHROMIUM, *BROWSER_FLAGS, f"--user-data-dir={folder / 'profile'}",
             "--window-size=1200,3000", "--remote-debugging-pipe"],
            log,
            timeout=120,
        )  # fmt: skip
        try:
            for name, html in pages.items():
                here = folder / name
                here.mkdir()
                page = here / f"{name}_report.html"
                page.write_text(html)
                _paint(browser, page, here)
            (folder / "returncode").write_text(str(browser.close()))
        finally:
            browser.kill()


@pytest.fixture(scope="module")
def painted() -> Path:
    """Every example's report (and the probed car's) as a browser showed it (made once per
    run, see above)."""
    if CHROMIUM is None:
        pytest.skip("chromium is not installed (`.ci/run` installs Debian's chromium as root)")
    return shared("report-in-a-browser", _paint_every_example)


def _shown_without_fault(painted: Path, name: str) -> str:
    """The DOM of page ``name`` after checking that the browser ended well and that no
    page said anything (the log is the browser's: any page's fault fails every test)."""
    stderr = (painted / "stderr").read_text(encoding="utf-8", errors="replace")
    assert (painted / "returncode").read_text() == "0", stderr[-2000:]
    console = [line for line in stderr.splitlines() if "CONSOLE" in line]
    assert console == []
    assert "ERR_NAME_NOT_RESOLVED" not in stderr and "net::ERR" not in stderr
    said = json.loads((painted / name / "said.json").read_text())
    assert said == []  # its console, an exception, a resource that failed to load
    return (painted / name / "dom.html").read_text(encoding="utf-8")


@pytest.mark.parametrize("name", EXAMPLES)
def test_html_renders_in_a_browser(name: str, painted: Path) -> None:
    dom = _shown_without_fault(painted, name)
    shot = painted / name / "shot.png"
    assert shot.read_bytes().startswith(b"\x89PNG") and shot.stat().st_size > 50_000
    headings = re.findall(r"<h2>(.*?)</h2>", dom)
    assert headings == list(HEADINGS)
    assert dom.count("<math") >= 15
    assert '<mtable class="matrix">' in dom  # matrices typeset as MathML tables


@pytest.mark.parametrize("name", EXAMPLES)
def test_html_is_self_contained(name: str) -> None:
    html = _html(name)
    assert "<script" not in html
    assert not re.search(r"""(src|href)\s*=\s*["'](?!#|data:)""", html)
    assert "http://" not in html and "https://" not in html and "@import" not in html


@pytest.mark.parametrize("name", EXAMPLES)
def test_markdown_twin_has_the_same_sections_and_math(name: str) -> None:
    d = derivation(name)
    md = render_report(d, kernels(name), formats=("md",))[f"{name}_report.md"]
    assert re.findall(r"^## (.*)$", md, re.M) == list(HEADINGS)
    # Key quantities appear as SymPy's own LaTeX of the derived objects (a mass-matrix
    # plant's run-time symbols under their display names, a_i and W_i,j), which the
    # report prints without SymPy.
    shown = _shown(d)
    for quantity in (
        d.linearization.R.xreplace(shown),
        d.decoupling.p.xreplace(shown),
        d.objective.gradient,
        d.hessian,
        d.model.f0,
    ):
        assert _latex(quantity) in md
    if d.model.mechanics is not None:
        assert "M is factored at run time, never inverted" in md
        for matrix in (d.model.mechanics.mass_matrix, d.model.mechanics.input_matrix):
            assert _latex(sx.matrix(matrix)) in md
        assert "_W0" not in md and "_ddq" not in md
    if d.decoupling.det_R is not None:
        assert _latex(d.decoupling.det_R) in md
    # Every display formula is structurally sound LaTeX.
    for formula in re.findall(r"\$\$(.*?)\$\$", md, re.S):
        assert formula.count("{") == formula.count("}")
        assert formula.count(r"\left") == formula.count(r"\right")
        assert formula.count(r"\begin{") == formula.count(r"\end{")


def test_report_contents_for_the_unicycle() -> None:
    md = render_report(derivation("unicycle_switch"), kernels("unicycle_switch"), formats=("md",))[
        "unicycle_switch_report.md"
    ]
    assert "R is singular when v = 0." in md
    assert "generic rank 1 &lt; 2" in md  # why the extension is needed (markup escaped)
    assert r"c = sup_t \|expm(H t)\| e^(alpha t), computed | 5.09902" in md
    assert "Theorem used: Theorem 5, Control Law for Uniform Vector Relative Degree Systems" in md
    assert "(eq. (18))" in md and "The implicit law (paper, eq. (17))" in md
    assert "No simulation results beside this report" in md


@pytest.mark.parametrize("fmt", ["md", "html"])
def test_golden_unicycle_report(fmt: str, update_golden: bool) -> None:
    name = f"unicycle_switch_report.{fmt}"
    text = render_report(_fixed("unicycle_switch"), kernels("unicycle_switch"), formats=(fmt,))[
        name
    ]
    golden = GOLDEN / name
    if update_golden:
        golden.write_text(text, encoding="utf-8")
    assert golden.exists(), f"missing {golden}: run `make update-golden`"
    assert text == golden.read_text(encoding="utf-8"), (
        f"{name} changed: review, then run `make update-golden` and commit"
    )


def test_non_uniform_law_cites_theorem_6() -> None:
    from .conftest import SPECS

    spec = str(SPECS / "nonuniform.toml")
    md = render_report(derivation(spec), kernels(spec), formats=("md",))["nonuniform_report.md"]
    assert "Theorem 6, Control Law for General Vector Relative Degree System" in md
    assert "xi_y1_1" in md and "eq. (19)" in md


def test_long_expressions_are_folded() -> None:
    html = render_report(
        derivation("two_unicycles_barrier"), kernels("two_unicycles_barrier"), formats=("html",)
    )["two_unicycles_barrier_report.html"]
    assert "<details><summary>Show the expression" in html


def test_report_command_includes_simulation_results(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    assert main(["simulate", "integrator", "--out", str(out), "--points", "41"]) == 0
    assert main(["report", "integrator", "--out", str(out)]) == 0
    assert "with the simulation results" in capsys.readouterr().out
    md = (out / "integrator_report.md").read_text()
    assert "certificate: PASSED" in md and "![Paths" in md
    html = (out / "integrator_report.html").read_text()
    assert html.count("data:image/png;base64,") == 3
    assert main(["report", "integrator", "--out", str(tmp_path / "md"), "--format", "md"]) == 0
    assert sorted(p.name for p in (tmp_path / "md").iterdir()) == ["integrator_report.md"]


def test_large_sparse_matrices_are_listed_by_entry(tmp_path: Path) -> None:
    # A ring of 10 agents: G, R, A, B and the Hessian are 20 x 20 or larger and mostly
    # zero. Each is listed by its nonzero entries (the symmetric Hessian by its lower
    # triangle), in the Markdown and as MathML tables in the HTML.
    from .test_index import ring

    m = 20
    d = derive(ring(m // 2))
    pages = render_report(d, lower(d), formats=("md", "html"))
    md, html = pages["unicycle_ring_report.md"], pages["unicycle_ring_report.html"]
    hess = d.hessian
    assert (
        f"Its Hessian ({m} x {m}, symmetric; the nonzero entries of its lower triangle, indexed "
        f"from 1; the other {sum(1 for e in hess if e == 0)} entries are 0):" in md
    )
    entry = r"\left[\nabla_{{yy}} f_0\right]_{{{}, {}}} &= {}"
    listed = [(i, j) for i in range(m) for j in range(i + 1) if hess[i, j] != 0]
    for i, j in listed[:5] + listed[-5:]:
        assert entry.format(i + 1, j + 1, _latex(hess[i, j])) in md
    i, j = next((i, j) for i in range(m) for j in range(i) if hess[i, j] == 0)
    assert entry.format(i + 1, j + 1, "") not in md
    assert r"\left[\nabla_{yy} f_0\right]_{1, 2} &=" not in md  # upper triangle: not listed
    assert _latex(hess) not in md  # not the dense matrix
    assert f"Decoupling matrix, rows L_G L_f^(r_i - 1) h_i (paper, eq. (2)) ({m} x {m}, its" in md
    # The MathML tables are well-formed XML, with HTML's named entities (&pi;) known to it.
    tables = re.findall(r"<math[^>]*><mtable><mtr><mtd><msub>.*?</math>", html, re.S)
    assert len(tables) >= 5
    for table in tables:
        for name in re.findall(r"&([A-Za-z]+;)", table):
            assert name in html5
        ElementTree.fromstring(re.sub(r"&[A-Za-z]+;", "", table))


def test_markup_in_the_description_stays_text_in_both_reports(tmp_path: Path) -> None:
    text = (ROOT / "tvopt_codegen" / "examples" / "integrator.toml").read_text()
    hostile = '<script>alert(1)</script> <img src=x onerror="alert(2)"> a & b'
    spec = write_spec(
        tmp_path, text.replace('description = """', f'description = """{hostile}\n', 1)
    )
    d = derive(load_spec(spec))
    files = render_report(d, lower(d))
    md = files["integrator_report.md"]
    assert "<script" not in md and "<img" not in md
    assert "&lt;script&gt;alert(1)&lt;/script&gt; &lt;img src=x onerror=" in md
    assert "a &amp; b" in md
    html = files["integrator_report.html"]
    assert "<script" not in html and "<img src=x" not in html


def test_matrices_have_css_brackets_and_names_keep_apart() -> None:
    files = render_report(derivation(CAR), kernels(CAR))
    html, md = files["kinematic_car_report.html"], files["kinematic_car_report.md"]
    assert '<mtable class="matrix">' in html and "<mo>[</mo><mtable" not in html
    assert "mtable.matrix {" in html  # the brackets, drawn at any height
    assert '<mo lspace="0.1667em" rspace="0.1667em">&InvisibleTimes;</mo>' in html
    assert r"\mathtt" not in md and r"wheelbase\," in md  # det R = v^2/(wheelbase cos^2)


def test_brackets_stretch_and_names_are_spaced_in_a_browser(painted: Path) -> None:
    # Measured in the page (PROBE): each matrix's bracket borders span its height, and in
    # det R the name "wheelbase" and the "cos" that follows it have a visible gap.
    dom = _shown_without_fault(painted, CAR_PROBE)
    found = re.search(r'<pre id="probe">(.*?)</pre>', dom)
    assert found is not None, dom[-500:]
    results = json.loads(found.group(1).replace("&quot;", '"'))
    matrices = [r for r in results if r[0] == "matrix"]
    assert matrices and all(bordered for _, bordered, _ in matrices)
    assert max(height for _, _, height in matrices) > 60  # a tall one: G, R, f~
    gaps = [r[1] for r in results if r[0] == "gap"]
    assert gaps and min(gaps) > 1.5  # pixels: a thin space, not glued together


def test_a_robust_spec_adds_a_section_per_option_with_h_i_the_observer_and_the_limits() -> None:
    from tvopt_codegen.report import ROBUST_HEADINGS

    from .conftest import SPECS

    spec = str(SPECS / "robust_pvtol.toml")
    md = render_report(derivation(spec), kernels(spec), formats=("md",))["robust_pvtol_report.md"]
    headings = re.findall(r"^## (.*)$", md, re.M)
    expected = list(HEADINGS)
    at = expected.index("Control law") + 1
    # All but the extended-state observer, which is refused beside the other observer.
    expected[at:at] = [h for h in ROBUST_HEADINGS if h != "Extended-state observer"]
    assert headings == expected
    robust = md.split("## Integral action")[1].split("## Generated code")[0]
    assert "## Disturbance observer" in robust and "## Actuator limits" in robust
    # The integral's pole, the nominal poles and the bumpless start; beta; the limits.
    assert "| lambda: the integral's pole (real, closest to zero) | -1 |" in robust
    assert "-3, -2.5, -2, -1.5" in robust
    assert "bandwidth beta = 20 rad/s" in robust and "every pole of sigma at -20" in robust
    assert "| thrust | 0 | 14.715 | 200 |" in robust and "| torque | -1 | 1 | inf |" in robust
    # H_I is the 5 x 5 companion matrix: its last row holds the five coefficients.
    assert "col(z_I, E)' = H_I col(z_I, E)" in md


def test_the_extended_state_observer_has_its_section_with_coordinates_and_poles() -> None:
    import tomllib

    from tvopt_codegen.spec import spec_from_dict

    with (ROOT / "tvopt_codegen" / "examples" / "drag_vehicle.toml").open("rb") as stream:
        data = tomllib.load(stream)
    data["robust"] = {"eso": {"bandwidth": 20.0}}
    d = derive(spec_from_dict(data))
    md = render_report(d, lower(d), formats=("md",))["drag_vehicle_report.md"]
    assert "## Extended-state observer" in md and "## Disturbance observer" not in md
    section = md.split("## Extended-state observer")[1].split("\n## ")[0]
    assert "omega = 20 rad/s" in section and "every pole of the estimation error at -20" in section
    # Per output: r_i = 4, the four estimates and d_hat, l_j = C(5, j) 20^j, -20 five times.
    row = "| x | 4 | eso_x_0, eso_x_1, eso_x_2, eso_x_3 | eso_x_d | "
    assert row + "100, 4000, 80000, 800000, 3.2e+06 | -20 (x5) |" in section
    assert "| y | 4 | eso_y_0, eso_y_1, eso_y_2, eso_y_3 | eso_y_d |" in section


def test_a_spec_with_limits_alone_adds_the_limits_section_alone() -> None:
    import tomllib

    from tvopt_codegen.derivation import derive
    from tvopt_codegen.lowering.ir import lower
    from tvopt_codegen.spec import spec_from_dict

    from .conftest import SPECS

    table = tomllib.loads((SPECS / "robust_pvtol.toml").read_text())
    del table["robust"]
    table["error_dynamics"]["poles"] = table["error_dynamics"]["poles"][1:]
    d = derive(spec_from_dict(table))
    md = render_report(d, lower(d), formats=("md",))["robust_pvtol_report.md"]
    headings = re.findall(r"^## (.*)$", md, re.M)
    assert headings[headings.index("Control law") + 1] == "Actuator limits"
    assert "Integral action" not in headings and "Disturbance observer" not in headings


def test_the_provenance_names_sympys_version_without_loading_it_or_its_metadata(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import importlib.metadata
    import importlib.util

    from tvopt_codegen.report import sections

    installed = importlib.metadata.version("sympy")
    assert sections._sympy_version() == installed == sp.__version__  # loaded: its own
    # Not loaded (a report on SymEngine): read from its release.py, found, not imported.
    monkeypatch.delitem(sys.modules, "sympy")
    assert sections._sympy_version() == installed
    assert "sympy" not in sys.modules
    # Where SymPy's files do not say: its metadata.
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    assert sections._sympy_version() == installed
