"""``acm-rs gapfill`` and ``acm-rs gapfill-eval`` subcommands."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from .filling import AUTO_WINDOW, METHODS


def _stage(msg: str, start: float) -> None:
    """One line per stage on stderr (the fill itself is one call into Rust)."""
    print(
        f"acm-rs gapfill: {msg} ({time.perf_counter() - start:.1f} s)", file=sys.stderr, flush=True
    )


def _read_report(m, chosen: np.ndarray) -> list[str]:
    """Lines saying what was read as missing (per reason, over the ``chosen`` points) and which
    points are left as read (not markers)."""
    missing = np.isnan(m.xyz).any(axis=2) & chosen[None, :]
    why = [
        f"{name}: {int((mask & chosen[None, :]).sum()):,}"
        for name, mask in m.missing_reasons.items()
        if (mask & chosen[None, :]).any()
    ]
    lines = [
        f"read as missing: {int(missing.sum()):,} marker-frames"
        + (f" ({', '.join(why)})" if why else " (empty or NaN values)" if missing.any() else "")
    ]
    kinds = m.kinds or ["marker"] * len(m.labels)
    other: dict[str, int] = {}
    for j in np.flatnonzero(~chosen):
        other[kinds[j]] = other.get(kinds[j], 0) + 1
    if other:
        per = ", ".join(f"{k}s: {n}" for k, n in other.items())
        lines.append(
            f"skipped {int((~chosen).sum())} non-marker points ({per}), written back as read; "
            "--include-non-markers fills them too"
        )
    return lines


def _cmd_gapfill(args: argparse.Namespace) -> int:
    from .._io import check_output_path
    from .._native import AcmNumericalError
    from .filling import fill_markers
    from .io import check_output, read, sidecar_path, write_like

    src = Path(args.input)
    out = check_output_path(args.output, args.overwrite)
    if args.std:
        check_output_path(args.std, args.overwrite, "--std output")
    for o in [out] + ([Path(args.std)] if args.std else []):
        if o.suffix.lower() in (".trc", ".csv"):
            check_output_path(sidecar_path(o), args.overwrite, "sidecar")
    start = time.perf_counter()
    m = read(src)
    n_t, n_m = m.xyz.shape[:2]
    _stage(f"read {src}: {n_t:,} frames x {n_m} markers", start)
    if args.rate is not None:
        if m.rate is not None and abs(m.rate - args.rate) > 1e-9 * m.rate:
            raise ValueError(f"{src} says {m.rate:g} Hz; --rate {args.rate:g} disagrees")
        m.rate = args.rate
    check_output(out, m.rate)
    if args.std:
        check_output(args.std, m.rate)
    opts = {}
    if args.gamma is not None:
        opts["gamma"] = args.gamma
    if args.combine is not None:
        opts["combine"] = args.combine
    chosen = np.ones(n_m, dtype=bool) if args.include_non_markers else m.is_marker
    missing = np.isnan(m.xyz).any(axis=2) & chosen[None, :]  # (T, M) point-frames to fill
    if not chosen.any():
        raise ValueError(
            f"{src} holds no markers, only model outputs (C3D POINT:ANGLES, FORCES, ...); "
            "pass --include-non-markers to fill them"
        )
    report = _read_report(m, chosen)
    _stage(
        f"filling {int(missing.sum()):,} missing marker-frames with {args.method}"
        + (" and posterior SDs" if args.std else ""),
        start,
    )
    # the posterior SDs double the time and memory of the smoother: only when asked for
    try:
        if args.window is None:
            window = AUTO_WINDOW if n_t > 2 * AUTO_WINDOW else None
        else:
            window = args.window or None  # 0: one pass
        if window and window < n_t and args.method.startswith("lowdim"):
            _stage(f"smoothing in windows of {window:,} frames (bounded memory; --window)", start)
        res = fill_markers(m, include_non_markers=args.include_non_markers,
                           method=args.method, std=bool(args.std), empty="skip",
                           window=window, **opts)  # fmt: skip
    except AcmNumericalError as exc:
        raise ValueError(
            f"{src}: the {args.method} fill failed numerically ({exc}); try --method spline, "
            "or check the file for frozen or duplicated markers"
        ) from None
    # what the fill imputed: the missing coordinates it made finite (observed ones are kept;
    # the points not selected are written back as read)
    filled, imputed = res.filled, res.imputed
    _stage("filled", start)
    write_like(out, m, filled, filled=imputed)
    skipped = np.flatnonzero(missing.all(axis=0))
    n_filled = int(imputed.any(axis=2).sum())
    print(
        f"acm-rs gapfill: {src} ({n_t} frames, {int(chosen.sum())} "
        f"{'points' if args.include_non_markers else 'markers'}, "
        f"{int(missing.sum())} missing marker-frames) -> {out}: filled {n_filled} with "
        f"{args.method} in {time.perf_counter() - start:.1f} s"
    )
    for line in report:
        print(f"  {line}")
    if len(skipped):
        names = [m.labels[i] for i in skipped]
        print(f"  left missing (never observed): {', '.join(names)}")
    if args.std:
        std = res.std if res.std is not None else np.zeros_like(res.filled)
        write_like(Path(args.std), m, std)
        what = "posterior standard deviations" if res.std is not None else "zeros (no posterior)"
        print(f"  wrote {what} ({m.units or 'file units'}) to {args.std}")
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    from .._io import check_output_path
    from .evaluate import evaluate
    from .io import read

    out = Path(args.out)
    for name in ("gapfill_eval.json", "gapfill_error_vs_length.png"):
        check_output_path(out / name, args.overwrite)
    m = read(args.input)
    X = m.xyz
    if not np.isfinite(X).all():
        raise ValueError(f"{args.input} has missing values; the protocol needs a complete file")
    if args.max_frames:
        X = X[: args.max_frames]
    rate = args.rate or m.rate
    if not rate:
        raise ValueError("the frame rate is unknown; pass --rate")
    methods = args.methods.split(",") if args.methods else list(METHODS)
    bad = [x for x in methods if x not in METHODS]
    if bad:
        raise ValueError(f"unknown method(s) {bad}; expected {', '.join(METHODS)}")
    res = evaluate(X, rate, methods=methods, repeats=args.repeats, seed=args.seed)
    print(
        f"acm-rs gapfill-eval: {args.input}, {X.shape[0]} frames, {X.shape[1]} markers, "
        f"{args.repeats} repetitions, {res.gap_frames.size} removed marker-frames"
    )
    print(f"error = distance to the removed position, in {m.units or 'file units'}")
    print(res.table(m.units or "file units"))
    for meth, msg in res.failures.items():
        print(f"  {meth} failed: {msg}")
    res.save_json(out / "gapfill_eval.json")
    res.plot(out / "gapfill_error_vs_length.png")
    print(f"  wrote {out / 'gapfill_eval.json'} and {out / 'gapfill_error_vs_length.png'}")
    if args.print_json:
        print(json.dumps(res.summary(), indent=1))
    return 0


def add_subcommands(sub: argparse._SubParsersAction) -> None:
    """Register the gap-filling subcommands on the ``acm-rs`` parser."""
    g = sub.add_parser("gapfill", help="fill marker gaps in a C3D, TRC or CSV file")
    g.add_argument("input", help="input .c3d, .trc or .csv")
    g.add_argument("-o", "--output", required=True, help="output file (format from suffix)")
    g.add_argument(
        "--method", default="lowdim", choices=METHODS,
        help="lowdim (default): the smoother in the learned SVD subspace with the fixes of "
        "docs/gapfill.md; lowdim-paper: as published; the others are per-coordinate baselines",
    )  # fmt: skip
    g.add_argument("--gamma", type=float, help="subspace energy fraction (lowdim)")
    g.add_argument(
        "--combine", choices=("none", "residual", "auto"),
        help="how lowdim combines the smoother with a spline on short gaps: auto (default, "
        "threshold calibrated on probe gaps), residual (border residuals only), none",
    )  # fmt: skip
    g.add_argument(
        "--std", metavar="FILE",
        help="also compute the posterior standard deviations and write them to FILE (same "
        "format; opt-in: doubles the time and memory of the smoother)",
    )  # fmt: skip
    g.add_argument(
        "--rate", type=float, help="frame rate (Hz), needed for a TRC/C3D output of a CSV input"
    )
    g.add_argument(
        "--window", "--chunk", type=int, dest="window",
        help=f"smooth in windows of this many frames (bounded memory; the model is learned "
        f"from the whole recording and the result equals one pass); 0: one pass; default: "
        f"windows of {AUTO_WINDOW} frames above {2 * AUTO_WINDOW} frames",
    )  # fmt: skip
    g.add_argument(
        "--include-non-markers", action="store_true",
        help="also fill the C3D points that are not markers (model outputs listed in "
        "POINT:ANGLES, FORCES, MOMENTS, POWERS, SCALARS, REACTIONS); by default they are "
        "written back as read",
    )  # fmt: skip
    g.add_argument("--overwrite", action="store_true", help="replace an existing output")
    g.set_defaults(func=_cmd_gapfill)
    e = sub.add_parser("gapfill-eval", help="score gap-filling methods on a complete sequence")
    e.add_argument("input", help="complete .c3d, .trc or .csv")
    e.add_argument("--out", default="gapfill_eval", help="output folder")
    e.add_argument("--methods", help=f"comma-separated subset of {','.join(METHODS)}")
    e.add_argument("--repeats", type=int, default=3, help="gap patterns per method (3)")
    e.add_argument("--seed", type=int, default=0, help="seed of the first gap pattern (0)")
    e.add_argument("--rate", type=float, help="frame rate (Hz) if the file has none")
    e.add_argument("--max-frames", type=int, help="use only the first N frames")
    e.add_argument(
        "--print-json", action="store_true", help="also print the scores as JSON on stdout"
    )
    e.add_argument("--overwrite", action="store_true", help="replace existing results")
    e.set_defaults(func=_cmd_eval)
