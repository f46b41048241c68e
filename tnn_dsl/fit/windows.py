"""Windows of the windowed rollouts (multiple shooting): the automatic length and the cut of each experiment."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class _Window:
    exp: int
    start: int
    length: int
    succ: tuple[int, int] | None = None  # (successor window id, offset in this window)


MIN_WINDOW_SAMPLES = 50
"""Fewest samples in an automatic window (``TrainConfig.window=None``)."""


DEFAULT_WINDOW_S = 600.0
"""The automatic window (s) where the data are sampled at ``dt ≤ 12 s``."""


def auto_window(exps) -> float:
    """The automatic window length (s): ``max(600 s, 50·dt)`` with ``dt`` the coarsest sample time of ``exps``.

    600 s suits data sampled every second (the case study, TCLab); at 5-minute sampling (buildings) it would be
    3 samples, and a multiple-shooting window that short is all initial state: its loss falls while the
    free run gets worse (measured on Bacher & Madsen's TiTeTh: training free-run MAE 6.4 K with 600 s windows,
    1.4 K with 50 samples)."""
    dt = max(float(e.dt) for e in exps)
    return max(DEFAULT_WINDOW_S, MIN_WINDOW_SAMPLES * dt)


def _windows(exps, window_s: float) -> list[_Window]:
    out: list[_Window] = []
    for e_i, e in enumerate(exps):
        n = int(e.n_steps) if hasattr(e, "n_steps") else len(e.t)
        L = max(2, int(round(window_s / float(e.dt))) + 1)
        if n <= L:
            out.append(_Window(e_i, 0, n))
            continue
        starts = list(range(0, n - L + 1, L - 1))
        if starts[-1] + L < n:
            starts.append(n - L)
        ids = []
        for s in starts:
            ids.append(len(out))
            out.append(_Window(e_i, s, L))
        for a, b in zip(ids[:-1], ids[1:]):
            out[a].succ = (b, out[b].start - out[a].start)
    return out
