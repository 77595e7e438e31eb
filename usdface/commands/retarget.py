"""``usdface retarget AVATAR CAPTURE -o map.json|.csv``: the automatic retargeting map of eq. (4)."""

from __future__ import annotations

from pathlib import Path

from .personalize import add_transfer_options, transfer_kwargs


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "retarget", help="automatic facial retargeting map (capture ARKit shapes -> avatar shapes), eq. (4)",
        description="Compute the K x K weight map of Menzel et al. 2022 eq. (4): each personalized ARKit "
                    "shape approximated by a ridge-regularised combination of the avatar's own shapes. "
                    "Engines "
                    "(Live Link, Unity) can drive the avatar with it instead of a hand-made map.")
    add_transfer_options(p)
    p.add_argument("-o", "--output", required=True, help="map file: .json or .csv")
    p.add_argument("--force", action="store_true", help="overwrite the output")
    p.set_defaults(func=run)


def run(args) -> int:
    from .. import progress
    from ..errors import InputFileError, OutputExistsError
    from ..transfer import personalize_avatar
    from ..transfer.retarget import weight_map_csv, weight_map_json, write_text_atomic

    out = Path(args.output)
    if out.suffix.lower() not in (".json", ".csv"):
        raise InputFileError("unknown map format", path=out, fix="use a .json or .csv output file")
    if out.exists() and not args.force:
        raise OutputExistsError("output exists", path=out, fix="pass --force to replace it")
    if args.quiet:
        progress.set_enabled(False)
    result = personalize_avatar(args.avatar, args.capture, None, **transfer_kwargs(args))
    if out.suffix.lower() == ".json":
        text = weight_map_json(result.weights, result.names, result.avatar_names,
                               meta={"avatar": str(args.avatar), "capture": str(args.capture), "mu": args.mu})
    else:
        text = weight_map_csv(result.weights, result.names, result.avatar_names)
    write_text_atomic(out, text)
    w = result.weights
    print(f"{w.shape[0]} x {w.shape[1]} retarget map -> {out} (weights in [{w.min():.2f}, {w.max():.2f}], "
          f"{int((abs(w) > 0.05).sum())} above 0.05)")
    return 0
