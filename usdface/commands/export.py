"""``usdface export LAYER --gltf out.glb [--obj-dir DIR] [--flatten out.usdc]``: deliver one variant of a
personalize result to engines, web viewers and tools that do not take USD layers."""

from __future__ import annotations

from .options import add_quiet


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "export", help="one variant of a personalize result as glTF (morph targets), OBJs or flattened USD",
        description="Export the composed avatar with the generic or personalized variant: glTF 2.0 with one "
                    "morph target per ARKit shape (names in mesh.extras.targetNames; metres, Y up; skin and "
                    "skeleton when the avatar has joints), a folder of OBJs (one full target mesh per "
                    "shape), and/or one flattened USD file with the variant baked in.")
    p.add_argument("layer", help="a layer written by 'usdface personalize' (or any UsdSkel avatar)")
    p.add_argument("--gltf", metavar="OUT",
                   help="glTF file to write (.glb binary, or .gltf with embedded data)")
    p.add_argument("--obj-dir", metavar="DIR",
                   help="folder to write: <mesh>/neutral.obj + <mesh>/<shape>.obj")
    p.add_argument("--flatten", metavar="OUT",
                   help="flattened USD file to write (.usdc/.usda/.usd, or .usdz: packaged by USD)")
    p.add_argument("--variant", choices=("personalized", "generic"), default=None,
                   help="which usdfacePersonalization variant to export (default: personalized; a plain "
                        "avatar, which has neither, exports as authored; asked for, a variant the file "
                        "lacks is refused)")
    p.add_argument("--no-skin", action="store_true", help="glTF without the skeleton and skin")
    p.add_argument("--no-morph-normals", action="store_true",
                   help="glTF morph targets without NORMAL deltas (POSITION only: about half the file, for "
                        "engines that recompute the normals of a posed mesh)")
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")
    p.add_argument("--allow-moved-neutral", action="store_true",
                   help="export a layer whose avatar's neutral was re-sculpted after it was written (refused "
                        "by default: its offsets were fitted and checked on the old neutral)")
    p.add_argument("--json", action="store_true",
                   help="print what was written as JSON (outputs, variant, warnings)")
    add_quiet(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from ..api import export_avatar
    from ..io.flatten import AS_AUTHORED, baked_variant, exported_variant

    if args.no_skin and not args.gltf and (args.obj_dir or args.flatten):   # it was silently ignored
        from ..errors import OptionError

        raise OptionError("--no-skin applies to the glTF only (OBJs carry no skin; a flattened USD keeps the "
                          "avatar's binding)", fix="drop --no-skin, or add --gltf OUT.glb")
    if args.no_morph_normals and not args.gltf:
        from ..errors import OptionError

        raise OptionError("--no-morph-normals applies to the glTF only (OBJ targets and a flattened USD "
                          "carry the shapes as authored)",
                          fix="drop --no-morph-normals, or add --gltf OUT.glb")
    done = export_avatar(args.layer, gltf=args.gltf, obj_dir=args.obj_dir, flatten=args.flatten,
                         variant=args.variant, skin=not args.no_skin, morph_normals=not args.no_morph_normals,
                         force=args.force, allow_moved_neutral=args.allow_moved_neutral)
    variant = exported_variant(args.layer, args.variant or "personalized")
    baked = baked_variant(args.layer)
    # a flattened export of a layer is exported as authored, with the shapes of the variant baked into it
    from ..io.usd_rig import dcc_export_marks, flattened_source

    dcc = variant == AS_AUTHORED and dcc_export_marks(args.layer)
    label = ("as authored: a DCC export of a usdface layer, the variant the DCC composed (personalized "
             "unless switched)" if dcc else
             # a fit rig said "a plain avatar, not personalized": it is the person's own shapes (stop 50)
             "as authored: a 'usdface fit' rig, the person's fitted shapes on the capture mesh"
             if variant == AS_AUTHORED and _is_fit_rig(args.layer) else
             "as authored: a plain avatar, not personalized" if variant == AS_AUTHORED else
             f"{variant}, as baked into {Path(args.layer).name} "
             f"(a flattened export of {flattened_source(args.layer, baked) or '?'})"
             if baked else variant)
    if args.json:
        import json

        from . import all_warnings, json_path

        print(json.dumps({"ok": True, "output": json_path(next(iter(done.values()), None)),
                          "outputs": {kind: json_path(path) for kind, path in done.items()},
                          "variant": variant, "label": label, "warnings": all_warnings([])}))
        return 0
    for kind, path in done.items():
        size = (f" ({path.stat().st_size / 1e6:.1f} MB)" if path.is_file() else
                f" ({sum(1 for _ in path.rglob('*.obj'))} OBJ files)")
        print(f"wrote {kind}: {path}{size} [{label}]")
    return 0


def _is_fit_rig(path) -> bool:
    """Whether ``path`` is a ``usdface fit`` result (its provenance's format), not an avatar."""
    from ..io.file_kind import Kind, file_kind

    return file_kind(path).kind is Kind.FIT
