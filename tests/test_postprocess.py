"""Filtering of localizations and merging of blinks (sparseloc.postprocess)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from sparseloc.io.tables import LOCS_COLUMNS, complete_locs
from sparseloc.postprocess import (
    MERGE_COLUMNS,
    _greedy_one_to_one,
    default_merge_distance,
    default_z_scale,
    filter_locs,
    link_blinks,
    merge_blinks,
)

# --------------------------------------------------------------------------------------------
# filtering
# --------------------------------------------------------------------------------------------


def _filter_table() -> pd.DataFrame:
    """Ten rows; row i fails exactly the criteria noted beside it (limits in the tests)."""
    rows = [
        # photons, sx, sy, sz, gof, z, flag
        (2000.0, 10.0, 10.0, 30.0, 1.0, 0.0, "ok"),  # 0 passes everything
        (100.0, 10.0, 10.0, 30.0, 1.0, 0.0, "ok"),  # 1 photons (too few)
        (90000.0, 10.0, 10.0, 30.0, 1.0, 0.0, "ok"),  # 2 photons (too many)
        (2000.0, 30.0, 10.0, 30.0, 1.0, 0.0, "ok"),  # 3 sigma_xy: sqrt((900+100)/2) = 22.4
        (2000.0, 10.0, 10.0, 90.0, 1.0, 0.0, "ok"),  # 4 sigma_z
        (2000.0, 10.0, 10.0, 30.0, 5.0, 0.0, "ok"),  # 5 gof
        (2000.0, 10.0, 10.0, 30.0, 1.0, 800.0, "ok"),  # 6 z
        (2000.0, 10.0, 10.0, 30.0, 1.0, 0.0, "z_edge"),  # 7 flag
        (100.0, 10.0, 10.0, 30.0, 5.0, 0.0, "diverged"),  # 8 flag, photons and gof
        (np.nan, 10.0, np.nan, 30.0, np.nan, 0.0, "ok"),  # 9 NaN photons, sigma_y, gof
    ]
    df = pd.DataFrame(
        rows,
        columns=["photons", "sigma_x_nm", "sigma_y_nm", "sigma_z_nm", "gof", "z_nm", "flag"],
    )
    df.insert(0, "frame", np.arange(len(df)))
    df.insert(1, "x_nm", 100.0 * np.arange(len(df)))
    df.insert(2, "y_nm", 50.0)
    return df


LIMITS = dict(
    photons_min=500.0,
    photons_max=50000.0,
    sigma_xy_max_nm=20.0,
    sigma_z_max_nm=60.0,
    gof_max=2.0,
    z_range=(-500.0, 500.0),
)


@pytest.mark.parametrize(
    "kwargs, removed_rows",
    [
        (dict(photons_min=500.0), [1, 8, 9]),
        (dict(photons_max=50000.0), [2, 9]),
        (dict(photons_min=500.0, photons_max=50000.0), [1, 2, 8, 9]),
        (dict(sigma_xy_max_nm=20.0), [3, 9]),
        (dict(sigma_z_max_nm=60.0), [4]),
        (dict(gof_max=2.0), [5, 8, 9]),
        (dict(z_range=(-500.0, 500.0)), [6]),
    ],
)
def test_each_criterion_removes_its_rows(kwargs, removed_rows):
    df = _filter_table()
    res = filter_locs(df, flags=None, **kwargs)
    assert sorted(set(range(len(df))) - set(res.locs["frame"])) == removed_rows
    (name,) = res.removed
    assert res.removed[name] == len(removed_rows)
    assert res.n_removed == len(removed_rows)


def test_flags_default_none_and_string():
    df = _filter_table()
    assert list(filter_locs(df).locs["frame"]) == [0, 1, 2, 3, 4, 5, 6, 9]
    assert filter_locs(df).removed == {"flag": 2}
    assert filter_locs(df, flags=None).n_kept == len(df)
    assert filter_locs(df, flags=None).removed == {}
    assert list(filter_locs(df, flags="z_edge").locs["frame"]) == [7]
    assert list(filter_locs(df, flags=["z_edge", "diverged"]).locs["frame"]) == [7, 8]


def test_all_criteria_counts_add_up_and_attribute_to_first_failure():
    df = _filter_table()
    before = df.copy()
    res = filter_locs(df, **LIMITS)
    assert list(res.locs["frame"]) == [0]
    # Row 8 fails flag, photons and gof: it counts against flag only; row 9 against photons.
    assert res.removed == {
        "flag": 2,
        "photons": 3,
        "sigma_xy": 1,
        "sigma_z": 1,
        "gof": 1,
        "z": 1,
    }
    assert sum(res.removed.values()) == res.n_removed == 9
    assert res.failed == {
        "flag": 2,
        "photons": 4,
        "sigma_xy": 2,
        "sigma_z": 1,
        "gof": 3,
        "z": 1,
    }
    assert res.summary().startswith("kept 1 of 10 localizations; removed 2 by flag, 3 by photons")
    pd.testing.assert_frame_equal(df, before)  # input untouched
    assert list(res.locs.columns) == list(LOCS_COLUMNS)
    assert res.locs["frame"].dtype == np.int64


def test_nan_only_matters_for_active_criteria():
    df = _filter_table()
    # Row 9 has NaN photons, sigma_y and gof but a finite sigma_z and z: kept by those.
    kept = filter_locs(df, flags=None, sigma_z_max_nm=60.0, z_range=(-500.0, 500.0)).locs
    assert 9 in set(kept["frame"])
    assert 9 not in set(filter_locs(df, flags=None, gof_max=100.0).locs["frame"])


def test_extra_columns_survive_filtering():
    df = _filter_table()
    df["track"] = np.arange(len(df)) * 10
    res = filter_locs(df, gof_max=2.0)
    assert list(res.locs.columns) == [*LOCS_COLUMNS, "track"]
    assert list(res.locs["track"]) == [0, 10, 20, 30, 40, 60]


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(photons_min=5000.0, photons_max=100.0), "photons_min"),
        (dict(z_range=(300.0, -300.0)), "reversed"),
        (dict(z_range=(0.0,)), "z_range"),
        (dict(sigma_xy_max_nm=-1.0), "sigma_xy_max_nm"),
        (dict(gof_max=np.nan), "gof_max"),
        (dict(flags=()), "flags"),
    ],
)
def test_filter_bad_arguments_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        filter_locs(_filter_table(), **kwargs)


def test_filter_missing_column_raises_naming_it():
    df = _filter_table().drop(columns=["gof", "sigma_z_nm"])
    with pytest.raises(ValueError, match="gof"):
        filter_locs(df, gof_max=2.0)
    with pytest.raises(ValueError, match="sigma_z_nm"):
        filter_locs(df, sigma_z_max_nm=50.0)
    assert filter_locs(df, photons_min=500.0).n_kept == 6  # columns not needed may be absent
    no_flag = df.drop(columns=["flag"])
    assert list(filter_locs(no_flag).locs["frame"]) == list(range(10))  # no flag column: all ok
    with pytest.raises(ValueError, match="DataFrame"):
        filter_locs(df.to_numpy())


# --------------------------------------------------------------------------------------------
# merging
# --------------------------------------------------------------------------------------------


def _locs(rows: list[tuple], **const) -> pd.DataFrame:
    """Table from (frame, x, y, z, sx, sy, sz, photons) rows."""
    df = pd.DataFrame(
        rows,
        columns=[
            "frame",
            "x_nm",
            "y_nm",
            "z_nm",
            "sigma_x_nm",
            "sigma_y_nm",
            "sigma_z_nm",
            "photons",
        ],
    )
    for k, v in const.items():
        df[k] = v
    return complete_locs(df)


def _two_molecules() -> pd.DataFrame:
    # A near (1000, 1000, 0): frames 0, 1, 2, dark 3, on 4. B near (6000, 3000, 200): frames
    # 2..6 (5 frames, no gap). Offsets of a few nm and unequal sigmas test the weighting.
    a = [
        (0, 1004.0, 998.0, 10.0, 10.0, 12.0, 30.0, 1000.0),
        (1, 980.0, 1003.0, -20.0, 20.0, 18.0, 60.0, 2000.0),
        (2, 1001.0, 1000.0, 5.0, 8.0, 9.0, 25.0, 3000.0),
        (4, 1010.0, 990.0, -5.0, 15.0, 15.0, 45.0, 1500.0),
    ]
    b = [
        (f, 6000.0 + 3 * (f - 4), 3000.0 - 2 * (f - 4), 200.0 + f, 12.0, 12.0, 35.0, 2500.0)
        for f in range(2, 7)
    ]
    df = _locs(a + b, background=np.array([10.0] * 4 + [20.0] * 5), sigma_photons=30.0)
    df.loc[1, "flag"] = "z_edge"
    return df.sample(frac=1.0, random_state=3).reset_index(drop=True)  # order must not matter


def test_merge_two_molecules_weighted_means():
    df = _two_molecules()
    before = df.copy()
    m = merge_blinks(df, max_distance_nm=50.0, max_gap=1)
    pd.testing.assert_frame_equal(df, before)
    assert list(m.columns) == list(MERGE_COLUMNS)
    assert len(m) == 2
    ra, rb = m.iloc[0], m.iloc[1]  # sorted by frame: A starts in frame 0, B in frame 2
    assert (ra["frame"], ra["last_frame"], ra["n_frames"]) == (0, 4, 4)
    assert (rb["frame"], rb["last_frame"], rb["n_frames"]) == (2, 6, 5)
    for row, members in ((ra, df[df["x_nm"] < 3000]), (rb, df[df["x_nm"] > 3000])):
        for ax in ("x", "y", "z"):
            w = 1.0 / members[f"sigma_{ax}_nm"] ** 2
            assert row[f"{ax}_nm"] == pytest.approx(np.sum(w * members[f"{ax}_nm"]) / w.sum())
            assert row[f"sigma_{ax}_nm"] == pytest.approx(1.0 / np.sqrt(w.sum()))
            assert row[f"sigma_{ax}_nm"] < members[f"sigma_{ax}_nm"].min()
        assert row["photons"] == pytest.approx(members["photons"].sum())
        assert row["sigma_photons"] == pytest.approx(30.0 * np.sqrt(len(members)))
        assert row["background"] == pytest.approx(members["background"].mean())
    # The weighted mean differs from the plain one here, so the weighting is really checked.
    assert abs(ra["x_nm"] - df[df["x_nm"] < 3000]["x_nm"].mean()) > 2.0
    assert ra["flag"] == "z_edge" and rb["flag"] == "ok"
    assert m["n_frames"].dtype == np.int64 and m["frame"].dtype == np.int64


def test_gap_longer_than_max_gap_splits():
    df = _two_molecules()
    m0 = merge_blinks(df, max_distance_nm=50.0, max_gap=0)  # A's dark frame 3 splits A
    assert sorted(m0["n_frames"]) == [1, 3, 5]
    rows = [(f, 0.0, 0.0, 0.0, 10.0, 10.0, 30.0, 1000.0) for f in (0, 1, 4, 5)]
    two_dark = _locs(rows)
    assert len(merge_blinks(two_dark, max_distance_nm=50.0, max_gap=1)) == 2
    assert len(merge_blinks(two_dark, max_distance_nm=50.0, max_gap=2)) == 1


def test_close_in_space_far_in_time_stay_separate():
    rows = [(f, 500.0 + f, 500.0, 0.0, 10.0, 10.0, 30.0, 1000.0) for f in (0, 1, 2, 20, 21)]
    m = merge_blinks(_locs(rows), max_distance_nm=50.0, max_gap=3)
    assert list(m["n_frames"]) == [3, 2]
    assert list(m["frame"]) == [0, 20]


def test_neighbours_on_together_are_assigned_one_to_one():
    # Two fluorophores 30 nm apart, both on in frames 0-3, with a 50 nm gate: each frame's
    # localization goes to the nearer track, so neither track swallows the other.
    rng = np.random.default_rng(0)
    rows = []
    for f in range(4):
        for x0 in (0.0, 30.0):
            rows.append((f, x0 + rng.normal(0, 2), rng.normal(0, 2), 0.0, 2.0, 2.0, 6.0, 1e3))
    m = merge_blinks(_locs(rows), max_distance_nm=50.0)
    assert list(m["n_frames"]) == [4, 4]
    assert m["x_nm"].to_numpy() == pytest.approx([0.0, 30.0], abs=3.0)


def test_axial_gate_and_z_scale():
    rows = [(0, 0.0, 0.0, 0.0, 5.0, 5.0, 20.0, 1e3), (1, 0.0, 0.0, 150.0, 5.0, 5.0, 20.0, 1e3)]
    df = _locs(rows)
    assert len(merge_blinks(df, max_distance_nm=50.0, z_scale=0.5)) == 2  # 150 > 50 / 0.5
    assert len(merge_blinks(df, max_distance_nm=50.0, z_scale=0.25)) == 1  # 150 <= 200
    assert len(merge_blinks(df, max_distance_nm=50.0, z_scale=0.0)) == 1  # z ignored


def test_default_distance_and_z_scale_rules():
    df = _locs([(0, 0.0, 0.0, 0.0, 10.0, 10.0, 40.0, 1e3)] * 3)
    assert default_merge_distance(df) == pytest.approx(4 * np.sqrt(2) * 10.0)
    assert default_z_scale(df) == pytest.approx(0.25)
    tiny = _locs([(0, 0.0, 0.0, 0.0, 1.0, 1.0, 4.0, 1e3)])
    assert default_merge_distance(tiny) == 20.0
    bare = complete_locs(pd.DataFrame({"frame": [0], "x_nm": [0.0], "y_nm": [0.0]}))
    assert default_merge_distance(bare) == 50.0
    assert default_z_scale(bare) == 0.5


def test_merge_without_sigmas_uses_50_nm_and_plain_means():
    df = pd.DataFrame(
        {"frame": [0, 1, 2, 3], "x_nm": [0.0, 40.0, 80.0, 200.0], "y_nm": [0.0, 0.0, 10.0, 10.0]}
    )
    m = merge_blinks(df)
    # 40 nm steps link (< 50 nm fallback), the 120 nm jump does not.
    assert list(m["n_frames"]) == [3, 1]
    assert m.loc[0, "x_nm"] == pytest.approx(40.0)
    assert m.loc[0, "y_nm"] == pytest.approx(10.0 / 3)
    assert np.isnan(m.loc[0, "sigma_x_nm"])
    assert list(m["flag"]) == ["ok", "ok"]


def test_merge_empty_table():
    m = merge_blinks(pd.DataFrame({"frame": [], "x_nm": [], "y_nm": []}))
    assert len(m) == 0
    assert list(m.columns) == list(MERGE_COLUMNS)
    assert m["frame"].dtype == np.int64 and m["n_frames"].dtype == np.int64
    assert m["x_nm"].dtype == np.float64


def test_link_labels_follow_input_rows():
    df = _two_molecules()
    labels = link_blinks(df, max_distance_nm=50.0)
    is_a = (df["x_nm"] < 3000).to_numpy()
    assert len(set(labels[is_a])) == 1 and len(set(labels[~is_a])) == 1
    assert labels[is_a][0] == 0 and labels[~is_a][0] == 1  # numbered by first frame


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(max_gap=-1), "max_gap"),
        (dict(max_gap=1.5), "max_gap"),
        (dict(max_distance_nm=0.0), "max_distance_nm"),
        (dict(z_scale=-0.5), "z_scale"),
    ],
)
def test_merge_bad_arguments_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        merge_blinks(_two_molecules(), **kwargs)


def test_greedy_matches_sequential_nearest_first():
    rng = np.random.default_rng(5)
    for _ in range(20):
        tracks = rng.uniform(0, 100, (12, 3))
        pts = rng.uniform(0, 100, (15, 3))
        ti, pj = np.nonzero(np.ones((12, 15), dtype=bool))
        keep = rng.random(ti.size) < 0.3
        ti, pj = ti[keep], pj[keep]
        at, ap = _greedy_one_to_one(ti, pj, tracks, pts, 12, 15)
        d = np.sum((tracks[ti] - pts[pj]) ** 2, axis=1)
        used_t, used_p, ref = set(), set(), set()
        for k in np.argsort(d, kind="stable"):
            if ti[k] not in used_t and pj[k] not in used_p:
                used_t.add(ti[k])
                used_p.add(pj[k])
                ref.add((ti[k], pj[k]))
        assert set(zip(at.tolist(), ap.tolist(), strict=True)) == ref


def test_simulated_blinking_recovers_molecule_count():
    rng = np.random.default_rng(11)
    n_mol, n_frames = 300, 600
    xyz = np.column_stack([rng.uniform(0, 10_000, (n_mol, 2)), rng.uniform(-500, 500, n_mol)])
    mol, frames = [], []
    for i, start in enumerate(rng.integers(0, n_frames, n_mol)):
        f = int(start)
        while True:
            length = rng.geometric(1 / 3)
            frames += range(f, f + length)
            mol += [i] * length
            f += length + 1
            if rng.random() >= 0.2:  # bleached; else dark for one frame, then on again
                break
    mol = np.array(mol)
    sig = np.array([15.0, 15.0, 40.0])
    noisy = xyz[mol] + rng.normal(size=(mol.size, 3)) * sig
    df = pd.DataFrame(
        {"frame": frames, "x_nm": noisy[:, 0], "y_nm": noisy[:, 1], "z_nm": noisy[:, 2]}
    ).assign(sigma_x_nm=15.0, sigma_y_nm=15.0, sigma_z_nm=40.0)
    assert len(merge_blinks(df, max_gap=0)) / n_mol > 1.1  # blinks split without a gap
    ratio = len(merge_blinks(df, max_gap=1)) / n_mol
    assert 0.97 < ratio < 1.05


def test_nonfinite_positions_stay_unmerged_and_extra_columns_dropped():
    rows = [(f, 0.0, 0.0, 0.0, 10.0, 10.0, 30.0, 1e3) for f in range(4)]
    df = _locs(rows)
    df.loc[1, "x_nm"] = np.nan
    df["note"] = "a"
    m = merge_blinks(df, max_distance_nm=50.0, max_gap=1)
    assert list(m.columns) == list(MERGE_COLUMNS)
    assert sorted(m["n_frames"]) == [1, 3]  # frames 0, 2, 3 link across the NaN row
    assert m["x_nm"].isna().sum() == 1
