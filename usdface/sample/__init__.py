"""Procedural sample assets with a known truth: ``usdface sample OUTDIR``.

:func:`generate_samples` writes, deterministically (same bytes for the same seed)::

    OUTDIR/
      README.txt             what is there, the main command, how to regenerate
      avatar.usda            UsdSkel avatar: /Avatar/{Head, Mouth, EyeLeft, EyeRight}, cm, Y up, head at
                             (0, 160, 2) cm; the 52 ARKit shapes as GENERIC blend shapes (sparse pointIndices)
      capture.usda           the person's capture as a USD asset (usdface.io.usd_capture, float32 geometry;
                             ARKit-like face mask, ~1,200 vertices, metres, centred near the origin): neutral,
                             template rig (GENERIC shapes on the mask, template identity), train + test frames
      capture/               only with ``folder=True`` (``usdface sample OUTDIR --folder``): the same capture
                             in the folder format: neutral.obj, template/, train/NNN_<shape>.obj+.json,
                             test/NNN.obj+.json (not in the committed sample_assets/: 8.8 MB of OBJ text)
      truth/capture_truth.npz  names, neutral, deltas (TRUE, metres), template_deltas, test_weights,
                               train_weights (noise-free weights; the capture holds the phone's noisy ones)
      truth/avatar_truth.npz   "Head/<shape>", "Mouth/<shape>" -> TRUE offsets on the avatar meshes (cm)
      truth/meta.json          parameters: seed, counts, units, the avatar -> capture transform, noise levels

Nothing is derived from third-party data: the head is an analytic surface (:mod:`.head`), the expressions
are smooth deformation fields (:mod:`.fields`), the person is a random identity plus personalised fields, the
weights follow cross-talk rules (:mod:`.performance`). A training / test frame is
``person neutral + sum_j w_j TRUE_j`` (true weights) plus scan noise; its JSON holds the phone's (noisy)
weights.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..arkit import ARKIT_NAMES
from ..model import Capture, FaceRig, Frames
from . import fields as F
from . import head as H
from . import performance as P

__all__ = ["generate_samples", "sample_take", "SampleParams", "build_samples", "artist_fields",
           "covered_vertices"]

#: Format version of the generated assets (bump when the generator changes the bytes on purpose).
SAMPLE_VERSION = 1


class SampleParams:
    """Fixed parameters of the sample case (units noted)."""

    capture_origin_cm = np.array([0.0, 1.0, 3.0])   # head-frame point that becomes the capture origin
    capture_tilt_deg = 3.0                           # capture frame pitched about X (face-anchor pose)
    scan_noise_m = 1e-4                              # 0.1 mm per coordinate
    weight_noise = 0.01                              # phone weight noise (std)
    capture_decimals = 6                             # metres: 1 micrometre
    avatar_decimals = 4                              # cm: 1 micrometre


def _rot_x(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


#: The capture's template rig: ``"generic"`` (the avatar's own generic shapes sampled on the mask, the
#: committed sample) or ``"artist"`` (another artist's rig, as a real phone app ships:
#: :func:`artist_fields`).
TEMPLATES = ("generic", "artist")


def artist_fields(generic: dict[str, list[dict]], seed: int) -> dict[str, list[dict]]:
    """Another artist's template rig for the same 52 ARKit shapes: the generic fields perturbed independently
    of the person and by more (amplitudes, directions, centres, widths, an extra component per shape), and a
    ``mouthClose`` authored to be used on top of ``jawOpen`` (it also carries the lower lip's jaw travel back
    up), so the template is further from the person than the avatar's own generic shapes are (the bench's
    ``dev3`` regime). Its own random stream (``seed``, 7), so the person and the committed sample's bytes do
    not depend on it."""
    rng = np.random.default_rng([seed, 7])
    out = F.personalize_fields(generic, rng, amplitude_std=0.45, tilt_deg=25.0, shift_std=0.45,
                               width_std=0.18, extra=0.35)
    out["mouthClose"] = out["mouthClose"] + [F._g((0.0, 0.6, 0.0), F._p(0, F.Y_MOUTH - 0.6), (2.0, 0.9, 1.4),
                                                  "lower")]
    return out


def _check_options(template: str, scan_noise_m, weight_noise, seed=0) -> None:
    """ValueError for a template not in :data:`TEMPLATES`, a negative noise (None: the default) or a seed that
    is not a whole number >= 0 (numpy's generator takes no other; a negative one failed deep inside it)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a whole number >= 0, not {seed!r}")
    if template not in TEMPLATES:
        raise ValueError(f"template must be one of {TEMPLATES}, not {template!r}")
    if not all(v is None or float(v) >= 0 for v in (scan_noise_m, weight_noise)):
        raise ValueError("scan_noise_m and weight_noise must be >= 0")


def covered_vertices(points, meta: dict, capture_points, capture_triangles) -> np.ndarray:
    """``[n]`` bool: the avatar vertices ``points[n,3]`` (internal metres) that a generated case's capture
    covers - within half a capture edge of the capture surface ``capture_points[c,3]``/``capture_triangles``
    (metres) once taken into the capture frame by ``meta["avatar_to_capture"]`` (``truth/meta.json``). The
    region the benchmark and the tests score the face and the seam on."""
    from ..transfer.surface import closest_points, mean_edge_length

    t = meta["avatar_to_capture"]
    cm = np.asarray(points, dtype=np.float64) / 0.01
    x = (cm - np.array(t["head_center_cm"]) - np.array(t["origin_cm"])) @ np.array(t["R"]).T / 100
    dist = closest_points(capture_points, capture_triangles, x)[3]
    return dist < 0.5 * mean_edge_length(capture_points, capture_triangles)


def build_samples(seed: int = 0, template: str = "generic", *, scan_noise_m: float | None = None,
                  weight_noise: float | None = None) -> dict:
    """Every array of the sample case, in memory (no files). Keys documented in :func:`generate_samples`;
    ``template``: one of :data:`TEMPLATES`; ``scan_noise_m`` (m per coordinate) and ``weight_noise`` (std of
    the phone's weights): None keeps :class:`SampleParams`' (the committed sample's 0.1 mm and 0.01; dev2's
    scan regime is about 0.15 mm and 0.03)."""
    _check_options(template, scan_noise_m, weight_noise, seed)
    scan_noise = SampleParams.scan_noise_m if scan_noise_m is None else float(scan_noise_m)
    weight_sigma = SampleParams.weight_noise if weight_noise is None else float(weight_noise)
    rng = np.random.default_rng(seed)
    sp = SampleParams
    names = list(ARKIT_NAMES)
    template_id = H.identity_params(rng)
    person_id = H.identity_params(rng)
    generic = F.generic_fields()
    true_fields = F.personalize_fields(generic, rng)

    # ---- capture (metres, capture frame): x_cap = R (X - origin) / 100
    R = _rot_x(sp.capture_tilt_deg)
    mask = H.capture_mask_mesh()
    Xc = mask.points()

    def to_cap(p_cm):
        return (p_cm - sp.capture_origin_cm) @ R.T / 100.0

    def to_cap_delta(d_cm):
        return d_cm @ R.T / 100.0

    dec = sp.capture_decimals
    person_neutral = np.round(to_cap(H.identity_warp(Xc, person_id)), dec)
    template_neutral = np.round(to_cap(H.identity_warp(Xc, template_id)), dec)
    # truth rounded (0.1 nm, 10 nm in cm below) so that regeneration gives the same bytes even where libm's
    # last bits differ between machines
    true_deltas = np.round(to_cap_delta(F.evaluate_fields(true_fields, Xc)), 10)
    template_fields = generic if template == "generic" else artist_fields(generic, seed)
    template_targets = np.round(template_neutral + to_cap_delta(F.evaluate_fields(template_fields, Xc)), dec)
    template_deltas = template_targets - template_neutral

    w_train = P.training_weights(rng)
    test_labels, w_test = P.test_weights(rng)
    w_true = np.concatenate([w_train, w_test])
    w_reported = P.reported_weights(rng, w_true, weight_sigma)
    frames = person_neutral + np.einsum("fk,knc->fnc", w_true, true_deltas)
    frames = np.round(frames + scan_noise * rng.standard_normal(frames.shape), dec)
    roles = ["train"] * len(w_train) + ["test"] * len(w_test)
    labels = [f"{j:03d}_{n}" for j, n in enumerate(names)] + [f"{i:03d}" for i in range(len(w_test))]
    tris = mask.triangles
    capture = Capture(person_neutral, tris, FaceRig(template_neutral, tris, names, template_deltas,
                                                    name="template"),
                      Frames(frames, w_reported, roles, labels), names,
                      metadata={"device": "usdface sample generator", "units_note": "metres"})

    # ---- avatar (cm world; rigs in metres internal)
    adec = sp.avatar_decimals
    head = H.avatar_head_mesh()
    Xh = head.points()
    head_neutral_cm = np.round(H.AVATAR_CENTER + H.identity_warp(Xh, person_id), adec)
    head_generic = np.round(F.evaluate_fields(generic, Xh), adec)
    head_true = np.round(F.evaluate_fields(true_fields, Xh), 6)
    mouth_pts, mouth_tris = H.mouth_block()
    mouth_neutral_cm = np.round(H.AVATAR_CENTER + H.identity_warp(mouth_pts, person_id), adec)
    mouth_names = [n for n in names if n in F.MOUTH_MESH_SHAPES]
    mouth_generic = np.round(F.evaluate_fields(generic, mouth_pts, "mouth", mouth_names), adec)
    mouth_true = np.round(F.evaluate_fields(true_fields, mouth_pts, "mouth", mouth_names), 6)
    rigs = [FaceRig(head_neutral_cm / 100.0, head.triangles, names, head_generic / 100.0, name="Head"),
            FaceRig(mouth_neutral_cm / 100.0, mouth_tris, mouth_names, mouth_generic / 100.0, name="Mouth")]
    for mesh_name, sign in (("EyeLeft", 1.0), ("EyeRight", -1.0)):
        c = H.identity_warp(H.eyeball_center(sign)[None], person_id)[0]
        pts, tri = H.uv_sphere(c, H.EYEBALL_RADIUS * person_id["scale"], 16, 10)
        pts = np.round(H.AVATAR_CENTER + pts, adec)
        rigs.append(FaceRig(pts / 100.0, tri, [], np.zeros((0, len(pts), 3)), name=mesh_name))
    avatar_truth = {f"Head/{n}": head_true[k].astype(np.float32) for k, n in enumerate(names)}
    avatar_truth.update({f"Mouth/{n}": mouth_true[k].astype(np.float32) for k, n in enumerate(mouth_names)})

    n_train = len(w_train)
    capture_truth = {"names": np.array(names), "neutral": person_neutral, "deltas": true_deltas,
                     "template_deltas": template_deltas, "test_weights": w_test, "train_weights": w_train}
    meta = {
        "generator": "usdface.sample", "sample_version": SAMPLE_VERSION, "seed": int(seed),
        "names": "canonical", "shapes": len(names),
        "capture_vertices": int(len(person_neutral)), "capture_triangles": int(len(tris)),
        "avatar_vertices": int(sum(r.n_vertices for r in rigs)),
        "avatar_meshes": {r.name: r.n_vertices for r in rigs},
        "train_frames": n_train, "test_frames": len(w_test), "test_expressions": test_labels,
        "units": {"capture": "m", "avatar": "cm (metersPerUnit 0.01)", "avatar_truth": "cm"},
        "avatar_to_capture": {
            "formula": "x_capture_m = R @ (x_avatar_cm - head_center_cm - origin_cm) / 100",
            "head_center_cm": H.AVATAR_CENTER.tolist(), "origin_cm": sp.capture_origin_cm.tolist(),
            "R": np.round(R, 12).tolist(), "tilt_about_x_deg": sp.capture_tilt_deg},
        "noise": {"scan_m": scan_noise, "weights": weight_sigma},
        "identity": {"template": template_id, "person": person_id},
    }
    if template != "generic":      # the committed sample's meta.json stays byte-identical
        meta["template"] = template
    return {"capture": capture, "rigs": rigs, "capture_truth": capture_truth, "avatar_truth": avatar_truth,
            "meta": meta, "true_weights": w_true, "head_mesh": head, "mask_mesh": mask}


def _write_npz(path: Path, arrays: dict) -> None:
    """Deterministic compressed npz (sorted keys; zip entries carry numpy's fixed timestamp)."""
    np.savez_compressed(path, **{k: arrays[k] for k in sorted(arrays)})


def _readme(meta: dict) -> str:
    """Text of ``README.txt`` in the generated folder: what is there and how to regenerate it."""
    seed = meta["seed"]
    seed_arg = f" --seed {seed}" if seed else ""
    lines = [
        f"usdface sample assets (seed {seed}), generated by usdface's own code (usdface/sample/);",
        "nothing is derived from third-party data.",
        "",
        "  avatar.usda    UsdSkel head avatar /Avatar (Head, Mouth, EyeLeft, EyeRight), cm, Y up,",
        f"                 {meta['shapes']} ARKit shapes (the GENERIC rig), "
        f"{meta['avatar_vertices']} vertices",
        f"  capture.usda   the person's capture (metres): neutral ({meta['capture_vertices']} vertices), "
        "template rig",
        f"                 as UsdSkel blend shapes, {meta['train_frames']} training + {meta['test_frames']} "
        "test frames as time samples",
        "  truth/         the person's TRUE blendshapes (capture_truth.npz, avatar_truth.npz), parameters",
        "                 (meta.json)",
        "",
        "Main job:",
        "  usdface personalize sample_assets/avatar.usda sample_assets/capture.usda -o person.usda",
        "",
        "Regenerate (byte-identical; tests/test_sample.py checks it):",
        f"  usdface sample sample_assets{seed_arg} --force",
        "",
        "The same capture as a raw capture folder (OBJ + JSON, docs/capture-format.md) is not committed",
        "(size); --folder writes it as OUTDIR/capture/ next to the same files:",
        f"  usdface sample OUTDIR{seed_arg} --folder",
        "",
        "Details: docs/sample-assets.md",
    ]
    return "\n".join(lines) + "\n"


def generate_samples(outdir, seed: int = 0, force: bool = False, folder: bool = False,
                     template: str = "generic", *, scan_noise_m: float | None = None,
                     weight_noise: float | None = None, take: bool = False) -> Path:
    """Generate the sample assets into ``outdir`` (see the module docstring); returns ``outdir``.

    Always writes ``README.txt``, ``avatar.usda``, ``capture.usda`` and ``truth/``; with ``folder=True`` also
    the raw capture folder ``capture/`` (the committed ``sample_assets/`` leaves it out to stay small). Every
    other file is the same with or without it. Deterministic: the same ``seed`` gives the same bytes.
    ``template="artist"``: the capture's template rig is another artist's (:func:`artist_fields`);
    ``scan_noise_m``, ``weight_noise``: the frames' noise (:func:`build_samples`). ``take=True``: also
    ``take.usdc``, a continuous take of the same person (:func:`sample_take`; every other file unchanged).
    Everything is assembled in a temporary folder next to ``outdir`` and renamed into place
    (:func:`usdface.io.atomic.replace_dir_atomically`); an existing non-empty ``outdir`` is refused unless
    ``force`` (OutputExistsError).
    """
    from ..io.atomic import check_output_dir, replace_dir_atomically
    from ..io.avatar_writer import write_rig_usd
    from ..io.capture_folder import write_capture_folder
    from ..io.usd_capture import write_capture_usd
    from ..progress import steps

    _check_options(template, scan_noise_m, weight_noise, seed)
    dest = check_output_dir(outdir, force)   # before the ~1 s of building
    with steps("sample", 4 + folder + take) as p, replace_dir_atomically(dest, force=force) as tmp:
        p.start("build avatar and capture")
        data = build_samples(seed, template, scan_noise_m=scan_noise_m, weight_noise=weight_noise)
        (tmp / "README.txt").write_text(_readme(data["meta"]))
        p.start("write avatar.usda")
        write_rig_usd(data["rigs"], tmp / "avatar.usda", up_axis="Y", meters_per_unit=0.01, root="/Avatar")
        p.start("write capture.usda")
        write_capture_usd(data["capture"], tmp / "capture.usda", exact=False)
        if folder:
            p.start("write capture folder")
            write_capture_folder(data["capture"], tmp / "capture")
        if take:
            from ..io.take import write_take_usd

            p.start("write take.usdc")
            write_take_usd(sample_take(data, seed), tmp / "take.usdc", exact=False)
        p.start("write truth")
        (tmp / "truth").mkdir()
        _write_npz(tmp / "truth" / "capture_truth.npz", data["capture_truth"])
        _write_npz(tmp / "truth" / "avatar_truth.npz", data["avatar_truth"])
        (tmp / "truth" / "meta.json").write_text(json.dumps(data["meta"], indent=1, sort_keys=True) + "\n")
    return dest


def sample_take(data: dict, seed: int = 0):
    """A continuous take of the sample person (``usdface sample OUTDIR --take``: ``take.usdc``), what a
    phone app records before ``capture select`` picks its peaks: every ARKit shape swept once in turn (1 s
    sweeps, 0.4 s rests, 30 fps, :func:`usdface.sample.take.make_take`'s defaults: ~2,250 frames, 75 s) by
    the person's TRUE rig on the capture mesh, with the capture's template and neutral, the sample's scan
    and weight noise (``data["meta"]["noise"]``: metres, weight units). ``data``: :func:`build_samples`.
    Returns the Take."""
    from ..model import FaceRig
    from .take import make_take

    truth, capture = data["capture_truth"], data["capture"]
    names = [str(n) for n in truth["names"]]
    person = FaceRig(truth["neutral"], capture.triangles, names, truth["deltas"])
    noise = data["meta"]["noise"]
    take, _ = make_take(person, capture.template.subset(names), point_noise=float(noise["scan_m"]),
                        weight_noise=float(noise["weights"]), seed=seed)
    return take
