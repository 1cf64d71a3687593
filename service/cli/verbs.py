"""CLI verbs for jobs on a server (``jobs``, ``wait``, ``start``, human ``status``) and the progress display.

Progress: a tqdm bar on a terminal; elsewhere (logs, CI, pipes) plain lines, one per 10 % of the masked pixels
or per 30 s, never carriage returns.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

from maxfs.storage.records import FINAL_STATES, JobState


def _hms(seconds: float | None) -> str:
    if seconds is None:
        return "--"
    return time.strftime("%H:%M:%S", time.gmtime(max(seconds, 0)))


def format_status(st: dict[str, Any]) -> str:
    """One line for a job's status as the server reports it."""
    p = st.get("progress") or {}
    done, total = p.get("tiles_done", 0), p.get("tiles_total", 0)
    frac = done / total if total else 0.0
    rate = p.get("pixels_per_second")
    if p.get("fraction") is not None:
        frac = p["fraction"]  # weighted by masked pixels (the server's)
    parts = [st["id"], *([st["name"]] if st.get("name") else []), f"{st['state']:<9}"]
    parts.append(f"tiles {done}/{total} ({frac:.0%})")
    if rate:
        parts.append(f"{rate / 1e3:.1f}k px/s")
    if st["state"] in (JobState.QUEUED, JobState.RUNNING):
        parts.append(f"ETA {_hms(p.get('eta_seconds'))}")
    if st["state"] in FINAL_STATES and p.get("pixels_done"):
        unfinished = max(p.get("pixels_total", 0) - p.get("pixels_done", 0), 0)
        shares = share_words(
            p.get("solved_share"), p.get("certified_share"), unfinished, p.get("pixels_total", 0)
        )
        if st.get("calibration"):  # an optimum proved for wrong lights is still wrong
            shares += " but calibration suspect (see the warnings)"
        parts.append(shares)
    if st.get("eps") is not None:
        parts.append(f"eps {st['eps']:.4g}{raw_step_words(st.get('raw_step'))}")
    line = "  ".join(parts)
    if st.get("error"):
        line += f"\n  error: {st['error']}"
    for w in st.get("warnings") or ():
        line += f"\n  warning: {w}"
    return line


def raw_step_words(step: int | None) -> str:
    """' (raw values in steps of 16)' where the images do not use every value of their type."""
    return f" (raw values in steps of {step})" if step and step > 1 else ""


def share_words(solved: float | None, certified: float | None, unfinished: int, total: int) -> str:
    """'solved 35.0 %, certified optimal 35.0 % of all masked pixels (13000 of 20000 not computed)':
    shares of the whole mask, naming the pixels of unfinished tiles when there are any."""
    if solved is None:
        return "no masked pixel solved"
    words = f"solved {solved:.1%}, certified optimal {certified or 0:.1%}"
    if unfinished:
        words += f" of all masked pixels ({unfinished} of {total} not computed)"
    return words


class Progress:
    """Tiles done out of total: tqdm on a terminal, plain lines otherwise."""

    def __init__(self, stream: Any = None, every: float = 30.0) -> None:
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.bar = None
        self.every = every
        self.last_line = 0.0
        self.last_decile = -1
        self.closed = False

    def update(
        self,
        done: int,
        total: int,
        state: str,
        rate: float | None = None,
        eta: float | None = None,
        pixels: tuple[int, int] | None = None,
    ):
        """Show ``done`` of ``total`` tiles; the share is of masked pixels solved (in finished tiles
        and so far in running ones) when ``pixels`` (done, total) is given, else of tiles."""
        if self.closed:
            return
        if not total and state not in FINAL_STATES:
            return  # queued, tiles not counted yet: a "0/0 tiles (0%)" line says nothing
        info = f"{state}" + (f", {rate / 1e3:.1f}k px/s" if rate else "")
        if self.tty:
            from tqdm import tqdm

            by_pixels = bool(pixels and pixels[1])
            if self.bar is None and total:
                # by masked pixels when they are known: a long tile moves the bar before it ends
                size, unit = (pixels[1], "px") if by_pixels else (total, "tile")  # type: ignore[index]
                self.bar = tqdm(
                    total=size,
                    unit=unit,
                    unit_scale=by_pixels,
                    file=self.stream,
                    dynamic_ncols=True,
                    leave=True,
                )
            if self.bar is not None:
                self.bar.n = min(pixels[0], self.bar.total) if by_pixels else done  # type: ignore[index]
                self.bar.set_postfix_str(
                    f"tiles {done}/{total}, {info}" if by_pixels else info, refresh=False
                )
                self.bar.refresh()
        else:
            frac = done / total if total else 0.0
            if pixels and pixels[1]:
                frac = pixels[0] / pixels[1]
            decile = int(10 * frac)
            now = time.monotonic()
            if decile != self.last_decile or now - self.last_line >= self.every or state in FINAL_STATES:
                eta_s = f", ETA {_hms(eta)}" if eta is not None and state not in FINAL_STATES else ""
                what = " of the masked pixels" if pixels and pixels[1] else ""
                print(f"{done}/{total} tiles ({frac:.0%}{what}), {info}{eta_s}", file=self.stream, flush=True)
                self.last_decile, self.last_line = decile, now
        if state in FINAL_STATES:
            self.close()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None
        self.closed = True

    # adapters
    def record(self, rec: Any) -> None:
        """``on_progress`` for :func:`service.runs.local.run_store` (a JobRecord)."""
        solved = rec.pixels_done + getattr(rec, "pixels_running", 0)
        eta = None
        if rec.pixel_rate and rec.pixels_total > solved:
            eta = (rec.pixels_total - solved) / rec.pixel_rate
        self.update(
            rec.tiles_done, rec.tiles_total, rec.state.value, rec.pixel_rate, eta, (solved, rec.pixels_total)
        )

    def status(self, st: dict[str, Any]) -> None:
        """``on_status`` for :meth:`service.cli.client.MaxfsClient.wait` (a status body)."""
        p = st.get("progress") or {}
        self.update(
            p.get("tiles_done", 0),
            p.get("tiles_total", 0),
            st["state"],
            p.get("pixels_per_second"),
            p.get("eta_seconds"),
            (p.get("pixels_done", 0) + p.get("pixels_running", 0), p.get("pixels_total", 0)),
        )


class UploadProgress:
    """Images sent by ``maxfs submit``: a tqdm bar on a terminal, nothing elsewhere (logs get the
    job id and, with ``--wait``, the job's progress lines)."""

    def __init__(self, k: int, stream: Any = None) -> None:
        self.k = k
        self.stream = stream or sys.stderr
        self.bar = None

    def __enter__(self) -> UploadProgress:
        return self

    def update(self, sent: int, k: int) -> None:
        if not bool(getattr(self.stream, "isatty", lambda: False)()):
            return
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(total=k, unit="image", desc="uploading", file=self.stream, dynamic_ncols=True)
        self.bar.n = sent
        self.bar.refresh()

    def __exit__(self, *exc: object) -> None:
        if self.bar is not None:
            self.bar.close()


def _client(args: argparse.Namespace):
    from maxfs.service.cli.common import make_client as make

    return make(args)


def cmd_status(args: argparse.Namespace) -> int:
    with _client(args) as c:
        st = c.status(args.job_id)
    print(json.dumps(st, indent=1) if args.json else format_status(st))
    return 0


def cmd_jobs(args: argparse.Namespace) -> int:
    with _client(args) as c:
        jobs = c.jobs()
    if args.json:
        print(json.dumps(jobs, indent=1))
    elif not jobs:
        print("no jobs", file=sys.stderr)
    else:
        for st in jobs:
            print(format_status(st))
    return 0


def wait_and_report(c: Any, job_id: str, as_json: bool) -> int:
    from maxfs.service.cli.common import EXIT_NOT_DONE

    st = c.wait(job_id, on_status=Progress().status)
    print(json.dumps(st, indent=1) if as_json else format_status(st))
    return 0 if st["state"] == JobState.DONE else EXIT_NOT_DONE


def cmd_wait(args: argparse.Namespace) -> int:
    with _client(args) as c:
        return wait_and_report(c, args.job_id, args.json)


def cmd_start(args: argparse.Namespace) -> int:
    with _client(args) as c:
        st = c.start(args.job_id)
        if args.wait:
            return wait_and_report(c, args.job_id, args.json)
    print(json.dumps(st, indent=1) if args.json else f"{args.job_id} {st['state']}")
    return 0


def version() -> str:
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as v

    try:
        return v("maxfs-ps")
    except PackageNotFoundError:
        return "unknown"
