"""Live Link Face CSV: names mapped by name (not position), timecodes, angles kept out, SkelAnimation."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from cli_helpers import _usdface
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import usdface.io  # noqa: F401  (registers the schemas before a test opens a stage)
from usdface.arkit import ARKIT_NAMES, livelink_name
from usdface.cli import main
from usdface.errors import CaptureError, InputFileError, UsdFaceError
from usdface.io.livelink import (
    ANGLE_COLUMNS,
    format_timecodes,
    parse_timecodes,
    read_livelink_csv,
    read_livelink_take,
    write_livelink_csv,
)
from usdface.io.usd_anim import read_skel_animation

# Live Link's own column order differs from Apple's (e.g. JawForward, JawRight, JawLeft).
LL_ORDER = list(ARKIT_NAMES)
LL_ORDER[15], LL_ORDER[16] = LL_ORDER[16], LL_ORDER[15]


def write_csv(path, weights, codes, names=LL_ORDER, angles=None):
    header = ["Timecode", "BlendShapeCount"] + [livelink_name(n) for n in names] + list(ANGLE_COLUMNS)
    angles = np.zeros((len(codes), len(ANGLE_COLUMNS))) if angles is None else angles
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for code, row, ang in zip(codes, weights, angles, strict=True):
            w.writerow([code, 61] + [f"{x:.10f}" for x in row] + [f"{a:.10f}" for a in ang])
    return path


def test_synthetic_take_maps_by_name(tmp_path):
    rng = np.random.default_rng(0)
    w = rng.random((4, 52))
    angles = rng.normal(size=(4, 9))
    codes = ["10:00:00:00.000", "10:00:00:02.000", "10:00:00:04.500", "10:00:01:00.000"]
    take = read_livelink_take(write_csv(tmp_path / "t.csv", w, codes, angles=angles))
    assert take.names == list(ARKIT_NAMES)  # ARKit order whatever the column order
    np.testing.assert_allclose(take.weights[:, ARKIT_NAMES.index("jawLeft")], w[:, LL_ORDER.index("jawLeft")],
                               atol=1e-10)
    np.testing.assert_allclose(take.times, [0, 2 / 60, 4.5 / 60, 1.0])
    assert list(take.angles) == list(ANGLE_COLUMNS)
    np.testing.assert_allclose(take.angles["HeadYaw"], angles[:, 0], atol=1e-10)
    names, weights, times = read_livelink_csv(tmp_path / "t.csv")
    assert names == take.names and weights.shape == (4, 52) and times.shape == (4,)


def test_timecodes_cross_midnight():
    t = parse_timecodes(["23:59:59:58.000", "00:00:00:00.000"], 60)
    np.testing.assert_allclose(t, [0, 2 / 60])


def test_bench_take(shared):
    take = read_livelink_take(shared / "data" / "livelinkface" / "S07-001.csv")
    assert take.weights.shape == (2028, 52) and take.names == list(ARKIT_NAMES)
    assert take.name_report["missing"] == []
    assert abs(take.fps - 30) < 0.5 and abs(take.times[-1] - 2028 / 30) < 1.0
    assert take.weights.min() >= 0 and take.weights.max() <= 1
    # 19 shapes never exceed 0.1 in this talking take (SOURCE.md)
    assert int((take.weights.max(axis=0) <= 0.1).sum()) == 19


def test_real_take_out_of_range_weights_clipped_with_warning(shared):
    with pytest.warns(UserWarning, match="eyeLookIn"):
        take = read_livelink_take(shared / "data" / "livelinkface" / "alex_rom_4.csv")
    assert take.weights.max() == 1.0


@pytest.mark.parametrize("mutate, error, words", [
    (lambda rows: [["Frame"] + rows[0][1:]] + rows[1:], InputFileError, "Timecode"),
    (lambda rows: rows[:1] + [rows[1][:-3]] + rows[2:], InputFileError, "line 2"),
    (lambda rows: rows[:2] + [[rows[2][0], "61", "abc"] + rows[2][3:]] + rows[3:], InputFileError, "line 3"),
    (lambda rows: rows[:2] + [[rows[2][0], "61", "nan"] + rows[2][3:]] + rows[3:], CaptureError, "NaN"),
    (lambda rows: [rows[0][:3] + ["EyeBlink_L"] + rows[0][4:]] + rows[1:], CaptureError, "several columns"),
    (lambda rows: [["13:00"] + r[1:] if i == 2 else r for i, r in enumerate(rows)], InputFileError, "HH:MM"),
    (lambda rows: rows[:1], InputFileError, "no frames"),
])
def test_bad_csv(tmp_path, mutate, error, words):
    codes = ["10:00:00:00.0", "10:00:00:02.0", "10:00:00:04.0"]
    p = write_csv(tmp_path / "t.csv", np.full((3, 52), 0.5), codes)
    with open(p) as fh:
        rows = list(csv.reader(fh))
    with open(p, "w", newline="") as fh:
        csv.writer(fh).writerows(mutate(rows))
    with pytest.raises(error) as info:
        read_livelink_take(p)
    assert words in str(info.value) and "t.csv" in str(info.value) and info.value.fix


def test_missing_file(tmp_path):
    with pytest.raises(InputFileError, match="not found"):
        read_livelink_csv(tmp_path / "none.csv")


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.text(alphabet="0123456789:.,-naeTimcod\n ", max_size=40), max_size=6))
def test_fuzz_raises_only_usdface_errors(tmp_path, lines):
    p = tmp_path / "fuzz.csv"
    p.write_text("Timecode,BlendShapeCount,EyeBlinkLeft,JawOpen\n" + "\n".join(lines))
    try:
        take = read_livelink_take(p)
    except UsdFaceError:
        return
    assert take.weights.shape == (len(take.times), len(take.names))
    assert np.isfinite(take.weights).all() and (take.weights >= 0).all() and (take.weights <= 1).all()


def test_anim_import_writes_skel_animation(tmp_path):
    from pxr import Usd

    rng = np.random.default_rng(1)
    w = rng.random((5, 52))
    codes = [f"10:00:00:{2 * i:02d}.000" for i in range(5)]
    src = write_csv(tmp_path / "t.csv", w, codes)
    out = tmp_path / "take.usda"
    assert main(["anim", "import", str(src), "-o", str(out)]) == 0
    stage = Usd.Stage.Open(str(out))
    prim = stage.GetDefaultPrim()
    assert prim.GetTypeName() == "SkelAnimation" and stage.GetTimeCodesPerSecond() == 60
    names, weights, time_codes = read_skel_animation(prim)
    take = read_livelink_take(src)
    assert names == take.names
    np.testing.assert_allclose(weights, take.weights, atol=1e-7)  # float[] in USD
    np.testing.assert_array_equal(time_codes, [0, 2, 4, 6, 8])
    assert prim.GetAttribute("usdface:curves:HeadYaw").GetTimeSamples() == [0, 2, 4, 6, 8]
    assert main(["anim", "import", str(src), "-o", str(out)]) == 2  # refuses to overwrite


def test_inspect_summarises_a_live_link_csv(tmp_path, capsys):
    """The docs say inspect summarises a weights-only take, and a Live Link CSV is one; inspect refused it
    ('a CSV file (a Live Link Face take?) where a USD avatar is expected')."""
    w = np.zeros((4, 52))
    w[1:3, LL_ORDER.index("jawOpen")] = [0.7, 0.9]
    codes = ["10:00:00:00.000", "10:00:00:02.000", "10:00:00:04.000", "10:00:00:06.000"]
    path = write_csv(tmp_path / "take.csv", w, codes)
    assert main(["inspect", str(path)]) == 0
    out = capsys.readouterr().out
    assert "take.csv: take" in out and "4 frames" in out and "never above 0.5 (51)" in out
    # Live Link's capitalised columns are its convention, one line (they were 52 "renamed (spelling)")
    assert "capitalised ARKit names (Live Link Face's columns): 52 (" in out and "renamed" not in out


def test_inspect_lists_a_real_rename_beside_live_links_capitalised_columns(tmp_path, capsys):
    names = [n if n != "jawOpen" else "jaw_open" for n in LL_ORDER]
    header = ["Timecode", "BlendShapeCount"] + [livelink_name(n) if n != "jaw_open" else n for n in names]
    rows = [[f"10:00:00:0{i}.000", 61] + ["0.5" if (i + k) % 7 == 0 else "0" for k in range(52)]
            for i in range(6)]
    path = tmp_path / "take.csv"
    with open(path, "w", newline="") as fh:
        csv.writer(fh).writerows([header] + rows)
    assert main(["inspect", str(path)]) == 0
    out = capsys.readouterr().out
    assert "capitalised ARKit names (Live Link Face's columns): 51 (" in out
    assert "renamed (1): jaw_open -> jawOpen" in out


def test_a_take_cut_off_mid_row_keeps_its_complete_rows(tmp_path):
    """User trial: a Live Link CSV cut mid-row (a recording that crashed) was refused whole ('line 246 has
    5 fields ... export again'), losing its 244 complete rows; the cut last line is dropped with a warning.
    A short row inside the file, or a complete short last line, is still refused."""
    w = np.random.default_rng(1).random((5, 52))
    codes = [f"10:00:00:{i:02d}.000" for i in range(5)]
    full = write_csv(tmp_path / "t.csv", w, codes).read_text()
    cut = tmp_path / "cut.csv"
    cut.write_text(full[: full.rstrip("\n").rfind("\n") + 40])         # the last row's first 39 characters
    with pytest.warns(UserWarning, match=r"last line is cut off .* 4 complete frames read"):
        take = read_livelink_take(cut)
    jaw = take.weights[:, ARKIT_NAMES.index("jawLeft")]
    np.testing.assert_allclose(jaw, w[:4, LL_ORDER.index("jawLeft")], atol=1e-9)
    cut.write_text(full[: full.rstrip("\n").rfind("\n") + 40] + "\n")  # ended by a line end: damaged
    with pytest.raises(InputFileError, match="fields"):
        read_livelink_take(cut)


def test_a_frame_field_at_or_above_the_default_rate_reads_at_the_implied_rate(tmp_path, capfd):
    """User trial: a 120 fps take ('10:00:00:95.000') read at the default 60 gave times past the next second
    and overlapping frames, silently. Read at the implied rate (the next common one above the largest
    field), with a warning naming the file, the rate and the option; a rate the caller gives that the
    timecodes contradict is refused. (Refusing the default too left take folders, CSVs given to fit or
    personalize and landmarks --takes, which take no rate, with no way to read a 120 fps take.)"""
    from usdface.errors import TimecodeError

    codes = ["10:00:00:00.000", "10:00:00:59.000", "10:00:00:95.000", "10:00:01:10.000"]
    p = write_csv(tmp_path / "t120.csv", np.full((4, 52), 0.5), codes)
    with pytest.warns(UserWarning, match=r"t120.csv: .* more than 95 frames per second: read at 120") as w:
        take = read_livelink_take(p)
    np.testing.assert_allclose(take.times, [0, 59 / 120, 95 / 120, 130 / 120])
    assert "--timecode-rate 120" in str(w[0].message)
    np.testing.assert_allclose(read_livelink_take(p, timecode_rate=120).times, take.times)
    with pytest.raises(TimecodeError) as info:                     # a rate given is checked
        read_livelink_take(p, timecode_rate=60)
    text = str(info.value)
    assert "t120.csv" in text and "not below the rate given, 60 (likely 120)" in text
    assert "--timecode-rate 120" in info.value.fix and "timecode_rate=120" in info.value.fix
    assert isinstance(info.value, InputFileError)
    with pytest.raises(TimecodeError, match="not below the rate given, 30"):
        parse_timecodes(["00:00:00:00", "00:00:00:30"], 30)
    out = tmp_path / "t.usda"
    assert main(["anim", "import", str(p), "-o", str(out), "--timecode-rate", "60"]) == 2
    assert not out.exists() and "--timecode-rate 120" in capfd.readouterr().err
    assert main(["anim", "import", str(p), "-o", str(out), "-q"]) == 0           # the default: read at 120
    said = capfd.readouterr()
    assert "read at 120 per second" in said.out + said.err
    from usdface.io.take import read_take

    with pytest.warns(UserWarning, match="read at 120"):               # a reader that takes no rate
        np.testing.assert_allclose(read_take(p).times, take.times)


def test_timecodes_round_trip_from_a_start_past_the_hour():
    """A take stamped with the time of day (Live Link Face's timecodes are wall-clock): formatted from a
    start past the hour, the codes read back to the same times, and each field is its own (minutes 0-59)."""
    times = np.array([0.0, 1 / 60, 2.5, 3600.25, 7322.5])
    codes = format_timecodes(times, 60.0, start="13:45:59:30.000")
    assert codes[0] == "13:45:59:30.000" and codes[3] == "14:45:59:45.000" and codes[4] == "15:48:02:00.000"
    np.testing.assert_allclose(parse_timecodes(codes, 60.0), times, rtol=0, atol=1e-9)


def test_a_frame_field_equal_to_a_common_rate_reads_at_the_next_one():
    """A field of 60 is the 61st frame of its second: the timecodes count above 60 per second (120), not at
    60."""
    with pytest.warns(UserWarning, match="read at 120"):
        times = parse_timecodes(["00:00:01:59.000", "00:00:01:60.000"])
    np.testing.assert_allclose(times, [0.0, 1 / 120], rtol=1e-12)


@pytest.mark.parametrize("code", ["10:00:-01:00.000", "10:00:00:-2.000", "-1:00:00:00.000"])
def test_a_negative_timecode_field_is_refused(tmp_path, code):
    from usdface.errors import TimecodeError

    p = write_csv(tmp_path / "neg.csv", np.full((3, 52), 0.5), ["10:00:00:00.000", code, "10:00:00:10.000"])
    with pytest.raises(TimecodeError, match=r"negative .* row 2|row 2 .* negative") as info:
        read_livelink_take(p)
    assert "neg.csv" in str(info.value) and info.value.fix


def test_a_rate_twice_the_timecodes_is_warned_about(tmp_path, recwarn):
    """Frame fields that never reach 30 over several seconds: the timecodes count at 30, and read at the
    default 60 every frame's time is wrong. Warned (naming the option); so is a rate given that is too high
    (user trial: ``--timecode-rate 120`` on a 30 fps take packed each second's frames into its first 0.25 s,
    silently, and the summary said ~60 Hz); the right rate is not warned."""
    times = np.arange(120) / 30.0                                  # 4 s at 30 fps
    p = write_csv(tmp_path / "t30.csv", np.full((120, 52), 0.5),
                  format_timecodes(times, 30.0))
    with pytest.warns(UserWarning, match=r"t30.csv: .*look like 30 per second.*--timecode-rate 30"):
        read_livelink_take(p)
    recwarn.clear()
    take = read_livelink_take(p, timecode_rate=30)
    np.testing.assert_allclose(take.times, times, atol=1e-9)
    assert not [w for w in recwarn if "30 per second" in str(w.message)]
    for rate in (60, 120):                                          # a rate given, too high for the codes
        with pytest.warns(UserWarning, match=rf"look like 30 per second, and read at the given rate {rate} "
                                             rf".*first {30 / rate:.2g} s"):
            read_livelink_take(p, timecode_rate=rate)
    recwarn.clear()
    # a real 60-rate take sampled at 30 Hz reaches frame fields up to 58: no warning
    q = write_csv(tmp_path / "t60.csv", np.full((120, 52), 0.5),
                  format_timecodes(times, 60.0))
    read_livelink_take(q)
    assert not [w for w in recwarn if "30 per second" in str(w.message)]


def test_real_takes_read_at_the_default_rate_without_a_rate_warning(shared, recwarn):
    for path in sorted((shared / "data" / "livelinkface").glob("*.csv")):
        read_livelink_take(path)
    assert not [w for w in recwarn if "per second" in str(w.message)]


def test_a_take_the_layer_plays_is_among_its_inputs(tmp_path):
    """``personalize --take`` plays the take in the layer's inspection animation: the take is recorded among
    the layer's inputs with its digest (it was not), so an edited take makes the layer stale, as an edited
    capture does."""
    from pathlib import Path

    from usdface.io.layers import stale_inputs
    from usdface.io.usd_rig import usdface_layer_data

    root = Path(__file__).resolve().parents[1] / "sample_assets"
    rng = np.random.default_rng(3)
    codes = [f"10:00:00:{f:02d}.000" for f in range(6)]
    take = write_csv(tmp_path / "t.csv", rng.random((6, 52)) * 0.5, codes)
    layer = tmp_path / "hero.usda"
    assert main(["personalize", str(root / "avatar.usda"), str(root / "capture.usda"), "-o", str(layer),
                 "--take", str(take), "-q"]) == 0
    data = usdface_layer_data(layer)
    assert take.resolve() in [(layer.parent / p).resolve() for p in data["inputs"]]   # relative to it
    assert len(data["inputDigests"]) == len(data["inputs"])
    assert stale_inputs(layer) == []
    write_csv(take, rng.random((6, 52)) * 0.5, codes)                    # the take edited afterwards
    stale = stale_inputs(layer)
    assert len(stale) == 1 and "t.csv" in stale[0] and "changed after it was written" in stale[0]


def test_anim_import_of_a_usd_binary_or_empty_file_says_what_it_is(tmp_path, capsys):
    """A user trial: 'anim import avatar.usdc' said "cannot read the CSV ('utf-8' codec can't decode byte 0xe3
    in position 16: invalid continuation byte)", and an empty .csv 'no Timecode column in the header'."""
    from pxr import Sdf

    usd = tmp_path / "take.usdc"
    Sdf.Layer.CreateNew(str(usd)).Save()
    binary = tmp_path / "scan.csv"
    binary.write_bytes(usd.read_bytes())
    empty = tmp_path / "empty.csv"
    empty.write_text("\n")
    for src, words in ((usd, "a USD file where a Live Link Face CSV is expected"),
                       (binary, "not a text CSV (byte 0x"), (empty, "the CSV is empty")):
        capsys.readouterr()
        assert main(["anim", "import", str(src), "-o", str(tmp_path / "out.usda")]) == 2
        err = capsys.readouterr().err
        assert words in err and "codec" not in err, err
        assert not (tmp_path / "out.usda").exists()


def test_anim_import_of_a_one_frame_take_says_so(tmp_path, capsys):
    """A user trial: a one-frame CSV was reported as '1 frames over 0.00 s (~30 Hz)'."""
    csv_path = write_csv(tmp_path / "one.csv", np.full((1, len(LL_ORDER)), 0.2), ["12:00:00:01.000"])
    assert main(["anim", "import", str(csv_path), "-o", str(tmp_path / "one.usda"), "-q"]) == 0
    out = capsys.readouterr().out
    assert "1 frame (no duration, no rate)" in out and "Hz" not in out, out


@pytest.mark.parametrize("swap", [False, True])
def test_rows_that_do_not_run_forward_are_refused(tmp_path, swap):
    """A CSV with a repeated timecode (an edited or merged take) was written as '99 frames' while the USD
    kept 98 (the two rows' time samples fell on one time code); rows out of order were reordered by USD but
    not in the take's weights (a user trial). Both are refused, naming the row."""
    from usdface.cli import main
    from usdface.errors import TimecodeError

    codes = [f"00:00:01:{f:02d}.000" for f in range(0, 40, 2)]
    if swap:
        codes[5], codes[6] = codes[6], codes[5]
    else:
        codes[6] = codes[5]
    with pytest.raises(TimecodeError, match=r"\(row 7 of the take\) (repeats|comes before) the previous"):
        parse_timecodes(codes, 60, "t.csv")
    header = "Timecode,BlendShapeCount,EyeBlinkLeft,JawOpen"
    (tmp_path / "t.csv").write_text("\n".join([header, *(f"{c},2,0.1,0.2" for c in codes)]) + "\n")
    assert main(["anim", "import", str(tmp_path / "t.csv"), "-o", str(tmp_path / "t.usda")]) == 2
    assert not (tmp_path / "t.usda").exists()


def test_anim_import_of_a_take_folder_names_the_csv_in_it(tmp_path, capsys):
    """``anim import take_dir`` (a folder of OBJ frames and its CSV) said 'Live Link CSV is a folder, not a
    file (fix: pass the .csv exported by Live Link Face)'; the fix now names the CSV in it (a user trial)."""
    from usdface.cli import main

    folder = tmp_path / "take dir"
    (folder / "frames").mkdir(parents=True)
    (folder / "take.csv").write_text("Timecode,BlendShapeCount,JawOpen\n00:00:00:00.000,1,0.5\n")
    assert main(["anim", "import", str(folder), "-o", str(tmp_path / "t.usda")]) == 2
    err = capsys.readouterr().err
    assert f"fix: pass the .csv exported by Live Link Face: {folder / 'take.csv'}" in err
    assert not (tmp_path / "t.usda").exists()


def test_take_frame_rate_is_the_rate_not_float_noise(tmp_path, capsys):
    """``inspect --json`` of a Live Link Face CSV said ``"fps": 30.000000000001705`` (one over the median
    interval of times summed from timecodes); the rate is rounded to 6 decimals, one rule for every take
    reader (the CSV's and the take folder's had the same code twice)."""
    import json

    from usdface.io.livelink import median_fps, read_livelink_take

    names = ["jawOpen", "eyeBlinkLeft"]
    csv = tmp_path / "t.csv"
    write_livelink_csv(csv, names, np.random.default_rng(0).uniform(0, 1, (200, 2)), np.arange(200) / 30.0)
    assert read_livelink_take(csv).fps == 30.0
    assert main(["inspect", str(csv), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["fps"] == 30.0
    assert median_fps(np.arange(5) * (1001 / 30000)) == 29.97003
    assert median_fps([0.0]) == 30.0 and median_fps([1.0, 1.0, 1.0]) == 30.0


def test_take_written_by_anim_import_is_a_take(tmp_path):
    """``personalize --take`` refused what ``anim import`` writes ('no mesh with time-sampled points')."""
    from usdface.io.livelink import write_livelink_csv
    from usdface.io.take import read_take

    w = np.linspace(0, 1, 12).reshape(6, 2)
    write_livelink_csv(tmp_path / "t.csv", ["jawOpen", "eyeBlinkLeft"], w, np.arange(6) / 60)
    assert main(["anim", "import", str(tmp_path / "t.csv"), "-o", str(tmp_path / "t.usda")]) == 0
    take = read_take(tmp_path / "t.usda")
    assert take.names == ["eyeBlinkLeft", "jawOpen"] or set(take.names) == {"jawOpen", "eyeBlinkLeft"}
    order = [["jawOpen", "eyeBlinkLeft"].index(n) for n in take.names]
    np.testing.assert_allclose(take.weights, w[:, order], atol=1e-6)
    np.testing.assert_allclose(take.times, np.arange(6) / 60, atol=1e-9)


def test_duplicated_live_link_column_is_refused(tmp_path):
    from usdface.errors import InputFileError
    from usdface.io.livelink import read_livelink_take

    p = tmp_path / "dup.csv"
    p.write_text("Timecode,BlendShapeCount,EyeBlinkLeft,EyeBlinkLeft\n00:00:00:00.000,2,0.1,0.2\n")
    with pytest.raises(InputFileError, match="duplicated column"):
        read_livelink_take(p)


@pytest.mark.parametrize("suffix", [".usda", ".usdc"])
def test_anim_import_force_overwrites(livelink_csv, tmp_path, suffix):
    out = tmp_path / f"t{suffix}"
    first = _usdface("anim", "import", livelink_csv, "-o", out, "-q", cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    out.write_bytes(b"stale")  # so the second write is seen to replace it
    again = _usdface("anim", "import", livelink_csv, "-o", out, "--force", "-q", cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    from pxr import Usd

    assert Usd.Stage.Open(str(out)).GetDefaultPrim().GetTypeName() == "SkelAnimation"
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name]
    refused = _usdface("anim", "import", livelink_csv, "-o", out, "-q", cwd=tmp_path)
    assert refused.returncode == 2 and "exists" in refused.stderr


def test_write_take_usd_force_overwrites(tmp_path):
    """The other take writer had the same missing ``force``."""
    from usdface.io.take import read_take_usd, write_take_usd

    take_file = tmp_path / "take.usda"
    take = _sample_take(tmp_path)
    write_take_usd(take, take_file)
    write_take_usd(take, take_file, force=True)
    assert len(read_take_usd(take_file).times) == len(take.times)


def _sample_take(tmp_path):
    import numpy as np

    from usdface.io.take import Take

    tri = np.array([[0, 1, 2]])
    pts = np.zeros((3, 3, 3))
    pts[:, 1, 0] = pts[:, 2, 1] = 0.01
    return Take(points=pts, triangles=tri, times=np.arange(3) / 30.0, weights=np.zeros((3, 1)),
                names=["jawOpen"])


def _header_variant(tmp_path, edit, name="t.csv"):
    codes = ["10:00:00:00.0", "10:00:00:02.0", "10:00:00:04.0"]
    p = write_csv(tmp_path / name, np.full((3, 52), 0.5), codes)
    p.write_text(edit(p.read_text()))
    return p


@pytest.mark.parametrize("edit", [
    lambda t: t.replace("BlendShapeCount", "BlendshapeCount", 1),   # another writer's spelling
    lambda t: t.replace("Timecode", "timecode", 1),
    lambda t: t.replace("\r\n", ",\r\n").replace("\n", ",\n") if "\r\n" in t else t.replace("\n", ",\n"),
    lambda t: t.split("\n", 1)[0].lower() + "\n" + t.split("\n", 1)[1],     # the whole header in lower case
])
def test_a_header_in_another_letter_case_or_lines_ending_in_a_comma_read_as_exported(tmp_path, edit, recwarn):
    """'BlendshapeCount' was warned about as a column that is no weight, a 'timecode' header refused as
    having no Timecode column, and lines ending with a comma (an empty last column) refused as 'column '':
    '' is not a number, the CSV is damaged' (a user trial). A header in lower case (stop 43's trial) read
    its weights but set the nine head and eye angles aside as unknown columns ('headyaw'), with a warning:
    they are the angles, in any letter case."""
    take = read_livelink_take(_header_variant(tmp_path, edit))
    assert take.weights.shape == (3, 52) and np.allclose(take.weights, 0.5)
    np.testing.assert_allclose(take.times, [0, 2 / 60, 4 / 60])
    assert not take.extra and not [w for w in recwarn if "neither ARKit" in str(w.message)]
    assert list(take.angles) == list(ANGLE_COLUMNS)


def test_a_semicolon_separated_csv_says_so(tmp_path):
    p = _header_variant(tmp_path, lambda t: t.replace(",", ";"))
    with pytest.raises(InputFileError, match="separated by semicolons") as info:
        read_livelink_take(p)
    assert "t.csv" in str(info.value) and "comma" in info.value.fix


def test_a_misspelt_weight_column_is_named_with_the_shape_it_looks_like(tmp_path):
    """'JawOpn' was warned about only as a column that is no weight; jawOpen then read 0 in every frame."""
    p = _header_variant(tmp_path, lambda t: t.replace("JawOpen", "JawOpn", 1))
    with pytest.warns(UserWarning, match=r"JawOpn \(looks like jawOpen: misspelt\?\).*JawOpn -> JawOpen"):
        take = read_livelink_take(p)
    assert "jawOpen" not in take.names and "JawOpn" in take.extra


def test_the_take_preflight_judges_a_csv_header_as_the_reader_does(tmp_path):
    """``usdface batch`` and the Pyblish validators check a take before any work
    (``usdface.io.take.check_take_path``): with its own header test, a take the reader reads (a 'timecode'
    header) would be refused there, and a semicolon-separated one refused without saying why."""
    from usdface.io.take import check_take_path

    lower = _header_variant(tmp_path, lambda t: t.replace("Timecode", "timecode", 1), "lower.csv")
    assert check_take_path(lower) == lower and len(read_livelink_take(lower).weights) == 3
    semi = _header_variant(tmp_path, lambda t: t.replace(",", ";"), "semi.csv")
    with pytest.raises(InputFileError, match="separated by semicolons"):
        check_take_path(semi)


def test_a_csv_of_no_arkit_weight_is_refused_naming_its_columns(tmp_path, capsys):
    """A CSV of head/eye angles only (or of another tool's curves) was written by 'anim import' as a take of
    '0 shapes' and played by 'personalize --take' as one holding every shape still."""
    p = tmp_path / "angles.csv"
    p.write_text("Timecode,BlendShapeCount,HeadYaw,CTRL_jaw\n10:00:00:00.0,2,0.1,0.2\n10:00:00:02.0,2,0.1,0.3\n")
    with pytest.warns(UserWarning, match="CTRL_jaw"), pytest.raises(CaptureError) as err:
        read_livelink_take(p)
    assert "no ARKit weight column" in err.value.message and "HeadYaw, CTRL_jaw" in err.value.message
    assert main(["anim", "import", str(p), "-o", str(tmp_path / "t.usda")]) == 2
    assert "no ARKit weight column" in capsys.readouterr().err and not (tmp_path / "t.usda").exists()


def test_an_unnamed_column_is_named_by_its_place(tmp_path):
    """pandas' ``to_csv`` writes its row index as a first column with no name: the warning about columns
    that are no weights ended in nothing ('not used as weights): ')."""
    def indexed(text):
        return "\n".join(("," if i == 0 else f"{i - 1},") + line if line else line
                         for i, line in enumerate(text.split("\n")))

    p = _header_variant(tmp_path, indexed)
    with pytest.warns(UserWarning, match=r"not used as weights\): a column with no name \(column 1\)"):
        take = read_livelink_take(p)
    assert take.weights.shape == (3, 52)


def test_median_fps_is_not_moved_by_a_gap():
    """A 30 fps take with one second missing in the middle is still 30 fps (the median interval), and a
    single frame is the 30 fps default."""
    from usdface.io.livelink import median_fps

    times = np.concatenate([np.arange(60) / 30.0, 3.0 + np.arange(60) / 30.0])
    assert median_fps(times) == 30.0
    assert median_fps([0.5]) == 30.0


def test_timecodes_past_midnight_keep_running_forward():
    """Every row after midnight is a day later, not the first one alone."""
    from usdface.io.livelink import parse_timecodes

    codes = ["23:59:59:58", "23:59:59:59", "00:00:00:00", "00:00:00:01", "00:00:00:02"]
    np.testing.assert_allclose(parse_timecodes(codes, 60.0), np.arange(5) / 60.0, rtol=0, atol=1e-12)


def test_livelink_weights_samples_frames_evenly_first_and_last_kept(tmp_path):
    from usdface.io.livelink import livelink_weights, write_livelink_csv

    names = ["jawOpen", "eyeBlinkLeft"]
    w = np.stack([np.arange(10) / 10.0, np.zeros(10)], axis=1)
    path = write_livelink_csv(tmp_path / "t.csv", names, w, np.arange(10) / 60.0)
    got = livelink_weights([path], ["eyeBlinkLeft", "jawOpen", "mouthClose"], frames=4)
    np.testing.assert_array_equal(got[:, 1], [0.0, 0.3, 0.6, 0.9])
    np.testing.assert_array_equal(got[:, [0, 2]], 0.0)
    assert len(livelink_weights([path], names, frames=10)) == 10
    assert len(livelink_weights([path], names, frames=9)) == 9


def test_format_timecodes_wraps_at_midnight():
    from usdface.io.livelink import format_timecodes

    assert format_timecodes([0.0, 1.0], 60.0, start="23:59:59:30") == ["23:59:59:30.000", "00:00:00:30.000"]


def test_a_nan_timecode_field_is_refused():
    from usdface.errors import TimecodeError
    from usdface.io.livelink import parse_timecodes

    with pytest.raises(TimecodeError, match="negative or non-numeric"):
        parse_timecodes(["00:00:01:00", "00:00:01:nan"], 60.0)


def test_animation_time_codes_range_rate_and_curves(tmp_path):
    """A take at 60 time codes per second: samples at ``times x 60``, the curves at the same codes, the
    stage's range the whole frames around them, its playback rate 60; authored after ``start_time_code``
    they shift by it; a layer with its own framesPerSecond for that rate keeps it; an animation with
    unsampled weights reads as one frame at code 0."""
    from pxr import Usd, UsdSkel, Vt

    from usdface.io.usd_anim import author_skel_animation, read_skel_animation, write_animation_usd

    names = ["jawOpen", "eyeBlinkLeft"]
    w = np.array([[0.1, 0.0], [0.5, 0.2], [0.9, 1.0]])
    times = np.array([0.0, 1.0, 2.5]) / 60.0
    curves = {"HeadYaw": [0.1, 0.2, 0.3]}
    path = write_animation_usd(tmp_path / "t.usda", names, w, times, 60.0, curves=curves)
    stage = Usd.Stage.Open(str(path))
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode(), stage.GetFramesPerSecond()) == (0.0, 3.0, 60.0)
    prim = stage.GetDefaultPrim()
    got_names, got_w, codes = read_skel_animation(prim)
    np.testing.assert_allclose(codes, [0.0, 1.0, 2.5], atol=1e-9)
    np.testing.assert_allclose(got_w, w, atol=1e-7)
    np.testing.assert_allclose(prim.GetAttribute("usdface:curves:HeadYaw").GetTimeSamples(), codes, atol=1e-9)
    other = Usd.Stage.CreateInMemory()
    other.SetTimeCodesPerSecond(60.0)
    other.SetFramesPerSecond(30.0)
    anim = author_skel_animation(other, "/A", names, w, 60.0, start_time_code=10.0)
    np.testing.assert_array_equal(anim.GetBlendShapeWeightsAttr().GetTimeSamples(), [10.0, 11.0, 12.0])
    assert (other.GetStartTimeCode(), other.GetEndTimeCode()) == (10.0, 12.0)
    assert other.GetFramesPerSecond() == 30.0
    still = UsdSkel.Animation.Define(other, "/Still")
    still.CreateBlendShapesAttr(Vt.TokenArray(names))
    still.CreateBlendShapeWeightsAttr().Set(Vt.FloatArray([0.25, 0.5]))
    _, sw, scodes = read_skel_animation(still.GetPrim())
    np.testing.assert_array_equal(scodes, [0.0])
    np.testing.assert_allclose(sw, [[0.25, 0.5]])
