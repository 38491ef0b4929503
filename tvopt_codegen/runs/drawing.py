"""Drawing the figures (:class:`~tvopt_codegen.runs.figures.Plot`) into PNG and SVG bytes.

Drawn on ``matplotlib.figure.Figure`` with the Agg canvas, never through pyplot or
``matplotlib.use``: a library user's plotting backend and open figures are left alone.

matplotlib's import is about as long as sympy's (0.6-0.9 s on this project's machine
class), and ``simulate`` needs both, one after the other. :class:`Painter` starts a
drawing process before the derivation: it imports matplotlib while this one imports
sympy, derives and runs the closed loop, and it draws the figures it is sent, each in
a process of its own, on the machine's other core. Where no process can be forked
(not POSIX, other threads running) or the drawing process fails, the figures are drawn
here: the bytes are the same.
"""

from __future__ import annotations

import contextlib
import io
import os
import signal
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tvopt_codegen.runs.side import can_fork, fork, receive, send, stop

#: The calls a panel may record: the ``matplotlib.axes.Axes`` methods the figures use.
AXES_CALLS = frozenset(
    {
        "plot",
        "semilogy",
        "step",
        "hist",
        "set_xlabel",
        "set_ylabel",
        "set_title",
        "set_xscale",
        "set_yscale",
        "set_ylim",
        "set_aspect",
        "grid",
        "legend",
    }
)

#: One recorded call: an ``Axes`` method's name, its positional and keyword arguments.
Call = tuple[str, tuple[Any, ...], dict[str, Any]]


class Panel:
    """One axes of a figure, recorded: ``panel.plot(t, y, lw=2)`` as matplotlib's ``Axes``.

    Only the calls of :data:`AXES_CALLS`; anything else is an ``AttributeError`` here,
    where the figure is described, not in the process that draws it.
    """

    def __init__(self) -> None:
        self.calls: list[Call] = []

    def __getattr__(self, name: str) -> Callable[..., None]:
        if name not in AXES_CALLS:
            raise AttributeError(f"a figure panel records no {name!r}")

        def record(*args: Any, **kwargs: Any) -> None:
            self.calls.append((name, args, kwargs))

        return record


@dataclass(frozen=True)
class Plot:
    """A figure as data (:mod:`tvopt_codegen.runs.figures` describes them), drawn in any process.

    Plain Python and NumPy arrays: the drawing process unpickles it without sympy.

    Attributes
    ----------
    stem : str
        File name without extension: the figure is written as ``<stem>.png`` and
        ``<stem>.svg``.
    size : tuple of float
        Width and height in inches.
    rows, cols : int
        The grid of panels.
    sharex : bool
        Whether the panels share the time axis.
    panels : list of Panel
        Row by row, each with its recorded calls.
    """

    stem: str
    size: tuple[float, float]
    rows: int = 1
    cols: int = 1
    sharex: bool = False
    panels: list[Panel] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.panels.extend(Panel() for _ in range(self.rows * self.cols - len(self.panels)))

    def file_names(self) -> tuple[str, str]:
        """The names of the figure's files: ``<stem>.png`` and ``<stem>.svg``."""
        return f"{self.stem}.png", f"{self.stem}.svg"


#: The margin around a figure's tight box, in inches (matplotlib's ``pad_inches``).
_PAD = 0.1
#: Pixels per inch of the PNG figures.
_DPI = 120

_SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


def _power_of_ten(value: float, _position: int | None = None) -> str:
    """``10⁻⁴`` for a decade, in plain text; nothing between decades."""
    if value <= 0:
        return ""
    exponent = np.log10(value)
    if abs(exponent - round(exponent)) > 1e-9:
        return ""
    return "10" + str(round(exponent)).translate(_SUPERSCRIPT)


def _plain_log_labels(fig: Any) -> None:
    """Label log axes in plain text.

    matplotlib's default log labels are mathtext (``$10^{-4}$``), which its parser reads
    anew for every figure: half of drawing a small ``simulate``'s figures.
    """
    from matplotlib.ticker import FuncFormatter, NullLocator  # noqa: PLC0415

    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            if axis.get_scale() == "log":
                axis.set_major_formatter(FuncFormatter(_power_of_ten))
                axis.set_minor_locator(NullLocator())


def draw(plot: Plot) -> dict[str, bytes]:
    """One figure as ``<stem>.png`` and ``<stem>.svg``, without what would vary by run.

    The figure is rendered once, at full size, on its Agg canvas; the tight box is found
    on that rendering, the PNG is cut from its pixels, and the SVG is written inside the
    same box. ``bbox_inches="tight"`` draws a figure once more per format to find the box,
    which tripled a small ``simulate``'s drawing time.
    """
    import matplotlib  # noqa: PLC0415 - only where figures are drawn
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: PLC0415
    from matplotlib.figure import Figure  # noqa: PLC0415
    from PIL import Image  # noqa: PLC0415

    fig = Figure(figsize=plot.size)
    # Any: matplotlib's Agg canvas methods carry no annotations.
    canvas: Any = FigureCanvasAgg(fig)
    axes = fig.subplots(plot.rows, plot.cols, sharex=plot.sharex, squeeze=False).ravel()
    for ax, panel in zip(axes, plot.panels, strict=True):
        for name, args, kwargs in panel.calls:
            # A title at its place, y = 1: left to place it, matplotlib measures every tick
            # label on every draw (a tenth of a figure's time) to lift a title over labels
            # on top, which no panel has (the bytes are the same).
            extra = {"y": 1.0} if name == "set_title" else {}
            getattr(ax, name)(*args, **(extra | kwargs))
    _plain_log_labels(fig)
    with matplotlib.rc_context({"svg.hashsalt": "tvopt-codegen", "svg.fonttype": "none"}):
        fig.set_dpi(_DPI)
        canvas.draw()
        box = fig.get_tightbbox(canvas.get_renderer()).padded(_PAD)
        png = io.BytesIO()
        Image.fromarray(_cut(np.asarray(canvas.buffer_rgba()), box)).save(
            png, format="png", dpi=(_DPI, _DPI)
        )
        svg = io.BytesIO()
        fig.savefig(svg, format="svg", dpi=_DPI, bbox_inches=box, metadata={"Date": None})
    return {f"{plot.stem}.png": png.getvalue(), f"{plot.stem}.svg": svg.getvalue()}


def _cut(pixels: np.ndarray, box: Any) -> np.ndarray:
    """The pixels inside ``box`` (inches from the bottom left), white where it overhangs.

    The padded tight box may reach past the canvas (a title at the top edge), as
    ``bbox_inches`` allows: the overhang is blank paper.
    """
    height, width = pixels.shape[:2]
    left, right = (round(v * _DPI) for v in (box.x0, box.x1))
    top, bottom = (height - round(v * _DPI) for v in (box.y1, box.y0))
    out = np.full((bottom - top, right - left, 4), 255, dtype=np.uint8)
    rows = slice(max(top, 0), min(bottom, height))
    cols = slice(max(left, 0), min(right, width))
    inside = pixels[rows, cols]
    out[rows.start - top :, cols.start - left :][: inside.shape[0], : inside.shape[1]] = inside
    return out


def draw_all(plots: Sequence[Plot]) -> dict[str, bytes]:
    """Every figure's files, in this process, in the order given."""
    files: dict[str, bytes] = {}
    for plot in plots:
        files.update(draw(plot))
    return files


def _load() -> None:
    """Import what drawing needs (the drawing process does it while the other derives)."""
    import matplotlib.backends.backend_agg  # noqa: F401, PLC0415
    import matplotlib.figure  # noqa: F401, PLC0415
    import matplotlib.ticker  # noqa: F401, PLC0415
    import PIL.Image  # noqa: F401, PLC0415
    import PIL.PngImagePlugin  # noqa: F401, PLC0415


#: What :meth:`Painter.collect` sends once every figure has been.
_DONE = "done"


def _fork_one(plot: Plot) -> tuple[int, int]:
    """A process drawing ``plot``: its pid and the pipe its files come back on."""
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the forked process, measured by its output
        try:
            os.close(read)
            send(write, ("ok", draw(plot)))
        except BaseException as error:  # noqa: BLE001 - reported to the parent, which redraws
            with contextlib.suppress(BaseException):
                send(write, ("error", repr(error)))
        finally:
            os._exit(0)
    os.close(write)
    return pid, read


def _serve(requests: int, replies: int) -> None:  # pragma: no cover - the drawing process
    """The drawing process: import matplotlib, draw what comes, each figure in its own child.

    A figure a child fails to draw comes back as an error, and the parent draws every
    figure itself (the same bytes, or the same exception where it belongs).
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the command's Ctrl-C is the parent's
    # Only the imports: a practice figure drawn here to warm the caches the figures'
    # processes inherit took 0.15 s and saved them 0.02-0.03 s each, and a small run's
    # figures arrive as matplotlib's import ends.
    _load()
    # Each batch is drawn as it comes (a run's first figures while it is certified).
    children: list[tuple[int, int]] = []
    while (batch := receive(requests)) != _DONE:
        if batch is None:
            return  # the command is gone
        children += [_fork_one(plot) for plot in batch]
    # In the order sent: a figure sent again (the run integrated again) is the last one.
    files: dict[str, bytes] = {}
    failed = None
    for pid, read in children:
        reply = receive(read)
        os.close(read)
        os.waitpid(pid, 0)
        if reply is None or reply[0] != "ok":
            failed = "a drawing process ended early" if reply is None else reply[1]
        else:
            files.update(reply[1])
    send(replies, ("error", failed) if failed is not None else ("ok", files))


class Painter:
    """Draws figures in a process started now, which imports matplotlib meanwhile.

    Use as a context manager around the work that produces the figures; :meth:`submit`
    sends them and :meth:`collect` returns their files. Leaving the block stops the
    process (killed if it was never given work: it was only importing).
    """

    def __init__(self) -> None:
        self._pid: int | None = None
        self._requests = self._replies = -1
        self._plots: list[Plot] = []
        if not can_fork():
            return
        self._pid, self._requests, self._replies = fork(_serve)

    def submit(self, plots: Sequence[Plot]) -> None:
        """Send figures to be drawn now; more may follow, and :meth:`collect` returns all.

        A figure sent again (the same stem) is drawn again, and its last drawing counts.
        """
        plots = list(plots)
        self._plots += plots
        if self._pid is not None and plots:
            try:
                send(self._requests, plots)
            except OSError:
                self._reap(kill=True)

    def collect(self) -> dict[str, bytes]:
        """The files of the figures submitted, in their order, however drawn."""
        # The last of each stem, in the order the stems were first sent.
        plots = list({plot.stem: plot for plot in self._plots}.values())
        self._plots = []
        if self._pid is None or not plots:
            return draw_all(plots)
        try:
            send(self._requests, _DONE)
            reply = receive(self._replies)
        except OSError:
            reply = None
        self._reap(kill=reply is None)
        if reply is None or reply[0] != "ok":
            return draw_all(plots)
        files: dict[str, bytes] = reply[1]
        # The children finish in any order; the files keep the plots' order.
        return {name: files[name] for plot in plots for name in plot.file_names()}

    def _reap(self, kill: bool) -> None:
        if self._pid is None:
            return
        pid, self._pid = self._pid, None
        stop(pid, (self._requests, self._replies), kill)

    def __enter__(self) -> Painter:
        return self

    def __exit__(self, *_exc: object) -> None:
        self._reap(kill=True)
