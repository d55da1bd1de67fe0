"""Progress of long runs as one small object, passed in by whoever wants to see it.

The light solve (inside ``jit``: called back once per iteration), a fit (once per step) and
the speed–accuracy study (once per run) all report through the same three methods, so a
caller picks how progress looks (nothing, a rewritten text line, a tqdm bar) in one place:

    meter.update(n, total=None, **values)   # n items done so far; values shown beside it
    meter.close()                           # end the line / bar

:class:`NoProgress` is the default of the Python API; the command line passes
:class:`TextProgress` when stderr is a terminal.  ``progress=True`` wherever a ``progress``
argument is taken means :func:`default_meter`.
"""

from __future__ import annotations

import abc
import sys


class AbstractProgressMeter(abc.ABC):
    """What every progress meter does; subclasses are final."""

    #: a short label (e.g. "light", "fit") shown before the count
    label: str = ""

    @abc.abstractmethod
    def update(self, n: int, total: int | None = None, **values: float) -> None:
        """``n`` items are done (of ``total`` if known); ``values`` are shown beside it."""

    @abc.abstractmethod
    def close(self) -> None:
        """Finish the display (a new line, a closed bar); the meter may be updated again."""

    # meters are compared and hashed by identity: a solver holding one stays hashable
    __hash__ = object.__hash__

    def __eq__(self, other):
        return self is other


class NoProgress(AbstractProgressMeter):
    """Shows nothing.  (All NoProgress meters are equal, so solvers holding one compare
    equal and share compiled code.)"""

    def __eq__(self, other):
        return isinstance(other, NoProgress)

    def __hash__(self):
        return hash(NoProgress)

    def update(self, n, total=None, **values):
        pass

    def close(self):
        pass


def _fmt(values: dict) -> str:
    return ", ".join(f"{k.replace('_', ' ')} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                     for k, v in values.items())


class TextProgress(AbstractProgressMeter):
    """One line on ``file`` (default stderr), rewritten in place at every update."""

    def __init__(self, label: str = "", file=None):
        self.label = label
        self.file = file
        self._open = False

    def update(self, n, total=None, **values):
        f = self.file or sys.stderr
        count = f"{int(n)}" + (f"/{int(total)}" if total else "")
        head = f"  {self.label} {count}" if self.label else f"  {count}"
        f.write(f"\r{head}: {_fmt({k: float(v) for k, v in values.items()})}   ")
        f.flush()
        self._open = True

    def close(self):
        if self._open:
            (self.file or sys.stderr).write("\n")
            self._open = False


class TqdmProgress(AbstractProgressMeter):
    """A tqdm bar on stderr (a total is needed for the bar; without one tqdm counts)."""

    def __init__(self, label: str = ""):
        self.label = label
        self._bar = None

    def update(self, n, total=None, **values):
        if self._bar is None:
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=self.label or None, file=sys.stderr, leave=True)
        self._bar.n = int(n)
        if values:
            self._bar.set_postfix_str(_fmt(values), refresh=False)
        self._bar.refresh()

    def close(self):
        if self._bar is not None:
            self._bar.close()
            self._bar = None


def default_meter(label: str = "") -> AbstractProgressMeter:
    """What ``progress=True`` means: a text line if stderr is a terminal, else nothing."""
    return TextProgress(label) if sys.stderr.isatty() else NoProgress()


def as_meter(progress, label: str = "") -> AbstractProgressMeter:
    """A meter from a ``progress`` argument: a meter as it is, True/False, or None (nothing)."""
    if isinstance(progress, AbstractProgressMeter):
        return progress
    if progress is True:
        return TextProgress(label)
    if progress in (False, None):
        return NoProgress()
    from ._errors import DifffogError

    raise DifffogError(f"progress must be True, False or a progress meter "
                       f"(difffog.TextProgress(), ...), got {progress!r}")


def sibling(progress, label: str) -> AbstractProgressMeter:
    """A meter for another phase of the same run (e.g. a fit's model error after its steps):
    one of the same kind with ``label``, or a user's own meter as it is."""
    meter = as_meter(progress, label)
    if isinstance(meter, NoProgress):
        return meter
    if type(meter) is TextProgress:
        return TextProgress(label, meter.file)
    if type(meter) is TqdmProgress:
        return TqdmProgress(label)
    return meter
