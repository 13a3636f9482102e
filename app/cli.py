"""Command line: ``aerograv simulate | inspect | process | evaluate | serve``.

Thin: parse arguments, call the pipeline, print where things are.  Every error ends the
command with one line ``error: …`` on stderr (on its own line, after any progress bar) and
exit code 2, and removes an ``--out`` folder the command created (``AEROGRAV_DEBUG=1`` shows
the traceback of an unexpected error).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

_BARS: list = []


class CommandError(Exception):
    """A user error found by the command line itself (bad option value)."""


def _progress_bar(desc: str):
    from tqdm import tqdm

    class _StageBar(tqdm):
        """The stage after the bar as it is (tqdm's own postfix comes with a leading ", ")."""
        stage = ""

        @property
        def format_dict(self):
            return {**super().format_dict, "stage": self.stage}

    bar = _StageBar(total=1000, desc=desc, unit="‰", bar_format="{desc}: {percentage:3.0f}%|{bar}| {stage}",
                    file=sys.stderr)
    _BARS.append(bar)
    state = {"stage": None}

    def progress(stage: str, fraction: float, info: dict | None = None):
        target = int(round(1000 * max(0.0, min(1.0, fraction))))
        if target > bar.n:
            bar.update(target - bar.n)
        post = stage
        if info and "em_iteration" in info:
            it = info["em_iteration"]
            post = f"EM it {it.get('iteration')} Q={_fmt(it.get('Q'))} R={_fmt(it.get('R'))}"
        if post != state["stage"]:
            bar.stage = post
            bar.refresh()
            state["stage"] = post
        if stage == "done":
            bar.close()

    return progress


def _fmt(v):
    try:
        return "[" + ", ".join(f"{float(x):.4g}" for x in v) + "]"
    except TypeError:
        return str(v)


def _close_bars() -> None:
    while _BARS:
        bar = _BARS.pop()
        try:
            bar.close()  # ends the bar's line: what follows starts on a line of its own
        except Exception:  # pragma: no cover
            pass


def _params(text: str | None) -> dict | None:
    """``--params``: a JSON object of ProcessingParams overrides, validated before any work."""
    if not text:
        return None
    try:
        obj = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise CommandError(f"--params is not valid JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise CommandError("--params must be a JSON object, e.g. '{\"m\": 1}'")
    from pydantic import ValidationError

    from app.config import ProcessingParams
    try:
        ProcessingParams.model_validate(obj)
    except ValidationError as exc:
        e = exc.errors()[0]
        where = ".".join(str(x) for x in e.get("loc", ())) or "params"
        raise CommandError(f"--params: {where}: {e.get('msg')} (got {str(e.get('input'))[:60]})") from None
    return obj


def cmd_simulate(args) -> int:
    from app.simulate import simulate_survey
    from app.simulate.presets import PRESETS

    if args.preset not in PRESETS:
        raise CommandError(f"unknown preset {args.preset!r}; choose one of {', '.join(sorted(PRESETS))}")
    path = simulate_survey(args.preset, args.out, seed=args.seed, progress=_progress_bar(f"simulate {args.preset}"))
    print(f"survey written to {Path(path).resolve()}")
    return 0


def cmd_inspect(args) -> int:
    import warnings

    from app.pipeline.inspect import inspect_survey

    with warnings.catch_warnings(record=True) as caught:   # the readers' warnings, said plainly
        warnings.simplefilter("always")
        table = inspect_survey(args.survey)
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    import pandas as pd

    with pd.option_context("display.max_rows", None, "display.max_columns", None, "display.width", 200):
        print(table.to_string(index=False))
    return 0


def cmd_process(args) -> int:
    from app.pipeline.parallel import freeze_imports
    from app.pipeline.process import process_survey

    freeze_imports()   # one run, then the process ends

    overrides = _params(args.params)
    if not Path(args.survey).is_dir():
        raise CommandError(f"survey directory {args.survey} not found")
    import warnings

    with warnings.catch_warnings(record=True) as caught:   # said once, below, not as Python's raw line
        warnings.simplefilter("always")
        try:
            report = process_survey(args.survey, args.out, overrides=overrides, progress=_progress_bar("process"))
        except Exception:
            # what the readers assumed before the failure often explains it (lat/lon that look like
            # radians, then "every line is too short"): said before the error line
            _close_bars()
            for w in dict.fromkeys(str(w.message) for w in caught):
                print(f"warning: {w}", file=sys.stderr)
            raise
    out = Path(args.out).resolve()
    cx = report.get("crossovers", {})
    print(f"outputs written to {out}")
    if "rms_before_mgal" in cx:
        print(f"crossover RMS: {cx['rms_before_mgal']:.3f} mGal before, {cx['rms_after_mgal']:.3f} mGal after leveling")
    said = list(report.get("warnings", []))
    said += [str(w.message) for w in caught if str(w.message) not in said]   # any the report lacks
    for w in said:
        print(f"warning: {w}", file=sys.stderr)
    return 0


def cmd_evaluate(args) -> int:
    from app.pipeline.evaluate import evaluate

    for p, what in ((Path(args.survey) / "truth", "the survey has no truth/ folder (only simulated surveys can be "
                                                   "evaluated)"), (Path(args.out) / "lines.parquet",
                                                                   f"{args.out} holds no outputs of `aerograv process`")):
        if not p.exists():
            raise CommandError(what)
    res = evaluate(args.survey, args.out)
    print(json.dumps(res, indent=2))
    return 0


def cmd_serve(args) -> int:
    from app.web.serve import serve

    serve(args.host, args.port, bootstrap=args.bootstrap)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="aerograv", description="Airborne gravimetry processing (SPEC.md)")
    sub = ap.add_subparsers(dest="cmd", required=True)

    from app.simulate.presets import PRESET_NOTES, PRESETS
    width = max(map(len, PRESETS))
    s = sub.add_parser("simulate", help="write a simulated survey directory (+ truth/)",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="presets (numbers in docs/SIMULATOR.md):\n" + "\n".join(
                           f"  {k:<{width}}  {PRESET_NOTES[k]}" for k in PRESETS))
    s.add_argument("--preset", required=True, metavar="PRESET",
                   help="a preset name (listed above)")
    s.add_argument("--out", required=True)
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(func=cmd_simulate)

    s = sub.add_parser("inspect", help="QC table per flight and line")
    s.add_argument("survey")
    s.set_defaults(func=cmd_inspect)

    s = sub.add_parser("process", help="process a survey directory into SPEC §5 outputs")
    s.add_argument("survey")
    s.add_argument("--out", required=True)
    s.add_argument("--params", default=None, help="JSON object of processing overrides, e.g. '{\"m\": 1}'")
    s.set_defaults(func=cmd_process)

    s = sub.add_parser("evaluate", help="score processed outputs against a simulated survey's truth/")
    s.add_argument("survey")
    s.add_argument("--out", required=True, help="the directory `aerograv process` wrote")
    s.set_defaults(func=cmd_evaluate)

    s = sub.add_parser("serve", help="start the web application")
    s.add_argument("--host", default="127.0.0.1")
    s.add_argument("--port", type=int, default=8000)
    s.add_argument("--bootstrap", default=None, help="survey directory imported and processed on first start")
    s.set_defaults(func=cmd_serve)

    args = ap.parse_args(argv)
    out = getattr(args, "out", None) if args.cmd in ("simulate", "process") else None
    created = out is not None and not Path(out).exists()
    try:
        return args.func(args)
    except BaseException as exc:  # noqa: BLE001 - every error ends as one line
        _close_bars()
        if created and Path(out).is_dir():
            shutil.rmtree(out, ignore_errors=True)  # nothing left behind by a failed command
        if isinstance(exc, SystemExit):
            raise
        if isinstance(exc, KeyboardInterrupt):
            print("\nerror: interrupted", file=sys.stderr)
            return 130
        if os.environ.get("AEROGRAV_DEBUG"):
            raise
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return 2


def _one_line(exc: BaseException) -> str:
    from app.io.errors import InputError

    if isinstance(exc, (InputError, CommandError)):
        msg = str(exc)
    elif isinstance(exc, (ValueError, OSError, KeyError, TypeError)) and str(exc):
        msg = f"{type(exc).__name__}: {exc}" if not isinstance(exc, ValueError) else str(exc)
    else:
        msg = f"{type(exc).__name__}: {exc} (set AEROGRAV_DEBUG=1 for the traceback)"
    return " ".join(msg.split())[:2000]


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
