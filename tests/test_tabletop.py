"""sim_fixtures.tabletop: the real osd-tabletop pairs (read from ../shared/data, skipped where
absent), the truth rule's properties on them and on small synthetic images, and the errors."""

from __future__ import annotations

import re

import numpy as np
import pytest
from scipy import ndimage

from hw.depth import Intrinsics
from sim_fixtures import UnknownScene
from sim_fixtures.tabletop import (
    MIN_REGION_PX,
    OBJECT_EDGE_PX,
    PAIRS,
    TRUTH_MARGIN_MM,
    TabletopDataMissing,
    changed_objects,
    drop_specks,
    fill_dropouts,
    footprint,
    load_tabletop_pair,
    tabletop_pairs,
    tabletop_truth,
)

README_PAIRS = [
    "test9-test10", "test10-test11", "test13-test14", "test14-test15", "test36-test37",
    "test37-test38", "learn38-learn39", "learn39-learn40", "learn40-learn41",
]
H, W = 480, 640
TABLE, OBJ_A, OBJ_B = 1, 20, 30


@pytest.fixture(scope="module")
def data_dir(shared_data):
    folder = shared_data / "osd-tabletop"
    if not folder.is_dir():
        pytest.skip(f"osd-tabletop not found in {shared_data}")
    return folder


@pytest.fixture(scope="module")
def pairs(data_dir):
    return {name: load_tabletop_pair(name, data_dir) for name in tabletop_pairs()}


def object_fractions(truth: np.ndarray, labels: np.ndarray) -> dict[int, float]:
    """{object id: fraction of its pixels that are truth}."""
    ids = np.unique(labels[labels >= 20] // 10)
    return {int(i): float(truth[labels // 10 == i].mean()) for i in ids}


# ---- the real pairs --------------------------------------------------------------------------

def test_names_are_the_readme_pairs():
    assert tabletop_pairs() == README_PAIRS


def test_descriptions_match_the_data_readme(data_dir):
    text = (data_dir / "README.md").read_text()
    rows = dict(re.findall(r"^\| (\w+ -> \w+) \| (.+?) \|$", text, flags=re.M))
    assert len(rows) == 9
    for name in tabletop_pairs():
        ref, cur, description = PAIRS[name]
        assert rows[f"{ref} -> {cur}"] == description


def test_all_pairs_load_with_shapes_and_dtypes(pairs):
    assert list(pairs) == README_PAIRS
    for name, p in pairs.items():
        assert p.name == name and p.description == PAIRS[name][2] == p.change and p.has_change
        for image in (p.reference, p.current, p.reference_labels, p.current_labels):
            assert image.shape == (H, W) and image.dtype == np.uint16
        for mask in (p.truth_appeared, p.truth_disappeared, p.footprint_reference,
                     p.footprint_current, p.crop_mismatch):
            assert mask.shape == (H, W) and mask.dtype == bool
        assert p.intrinsics == Intrinsics.openni_default() == Intrinsics(640, 480, 525.0, 525.0,
                                                                         319.5, 239.5)
        assert p.margin_mm == TRUTH_MARGIN_MM and p.min_region_px == MIN_REGION_PX
        assert [f.tolist() for f in p.reference_frames()] == [p.reference.tolist()]
        assert p.current_frames()[0] is p.current
        assert p.reference_paths[0].name == f"{p.reference_name}_depth_mm.png"
        assert p.current_paths[0].name == f"{p.current_name}_depth_mm.png"
        # label 0 is exactly "no point", as the data README says
        assert np.array_equal(p.reference == 0, p.reference_labels == 0)
        assert np.array_equal(p.current == 0, p.current_labels == 0)


def test_truth_is_object_pixels_only(pairs):
    for name, p in pairs.items():
        for truth, depth, labels in ((p.truth_appeared, p.current, p.current_labels),
                                     (p.truth_disappeared, p.reference, p.reference_labels)):
            assert (labels[truth] >= 20).all(), name
            assert (depth[truth] > 0).all(), name


def test_no_truth_on_table_pixels(pairs):
    for name, p in pairs.items():
        assert not (p.truth_appeared & (p.current_labels >= 1) & (p.current_labels <= 9)).any()
        assert not (p.truth_disappeared & (p.reference_labels >= 1)
                    & (p.reference_labels <= 9)).any(), name


def test_no_truth_where_the_frames_agree_within_the_margin(pairs):
    for name, p in pairs.items():
        r, c = p.reference.astype(int), p.current.astype(int)
        agree = (r > 0) & (c > 0) & (np.abs(r - c) <= TRUTH_MARGIN_MM)
        assert agree.sum() > 100_000
        assert not (p.truth_appeared & agree).any(), name
        assert not (p.truth_disappeared & agree).any(), name


def test_truth_sees_farther_in_the_other_frame(pairs):
    """Where the other frame has a reading, it is farther than the truth pixel by > margin."""
    for name, p in pairs.items():
        r, c = p.reference.astype(int), p.current.astype(int)
        a = p.truth_appeared & (r > 0)
        d = p.truth_disappeared & (c > 0)
        assert (r[a] > c[a] + TRUTH_MARGIN_MM).all(), name
        assert (c[d] > r[d] + TRUTH_MARGIN_MM).all(), name


def test_crop_differences_are_never_truth(pairs):
    for name, p in pairs.items():
        assert not (p.truth_appeared & ~p.footprint_reference).any(), name
        assert not (p.truth_disappeared & ~p.footprint_current).any(), name
        assert not ((p.truth_appeared | p.truth_disappeared) & p.crop_mismatch).any(), name
    # learn40 -> learn41: the crop differs at the right edge (thousands of pixels kept in only
    # one frame), and none of it is truth
    p = pairs["learn40-learn41"]
    right = np.zeros((H, W), bool)
    right[:, W // 2:] = True
    assert (p.crop_mismatch & right).sum() > 5000
    assert (p.footprint_current & ~p.footprint_reference).sum() > 5000


def test_truth_has_no_specks(pairs):
    for name, p in pairs.items():
        for truth in (p.truth_appeared, p.truth_disappeared):
            regions, n = ndimage.label(truth, structure=np.ones((3, 3)))
            if n:
                assert np.bincount(regions.ravel())[1:].min() >= MIN_REGION_PX, name


# (pair, appeared pixels, disappeared pixels) as measured when the rule was set (+-3 %)
COUNTS = [
    ("test9-test10", 1335, 5749), ("test10-test11", 17859, 7857),
    ("test13-test14", 1301, 12842), ("test14-test15", 14814, 0),
    ("test36-test37", 19177, 12180), ("test37-test38", 7342, 2131),
    ("learn38-learn39", 15996, 25280), ("learn39-learn40", 7710, 11233),
    ("learn40-learn41", 21942, 26192),
]


@pytest.mark.parametrize("name,appeared,disappeared", COUNTS)
def test_truth_pixel_counts(pairs, name, appeared, disappeared):
    p = pairs[name]
    assert p.truth_appeared.sum() == pytest.approx(appeared, rel=0.03, abs=5)
    assert p.truth_disappeared.sum() == pytest.approx(disappeared, rel=0.03, abs=5)


def test_added_objects_appear_whole(pairs):
    """test10 -> test11 (small box added in front), test14 -> test15 ("gittis" box added in
    front): one current object is >= 90 % appeared, and appeared >> 0."""
    for name in ("test10-test11", "test14-test15"):
        p = pairs[name]
        assert p.truth_appeared.sum() > 5000
        assert max(object_fractions(p.truth_appeared, p.current_labels).values()) >= 0.9


def test_removed_box_disappears(pairs):
    """test13 -> test14: the white box removed -> disappeared >> appeared (only slivers)."""
    p = pairs["test13-test14"]
    assert p.truth_disappeared.sum() > 5000
    assert p.truth_disappeared.sum() > 5 * p.truth_appeared.sum()


def test_hidden_box_is_not_disappeared(pairs):
    """test14 -> test15: the green box is hidden behind the added one, not seen through."""
    p = pairs["test14-test15"]
    assert p.truth_disappeared.sum() < 100


@pytest.mark.parametrize("name", ["test9-test10", "test37-test38"])
def test_one_object_moved_others_static(pairs, name):
    """Only one object moved: it holds >= 95 % of each truth; the others are <= 2 % truth."""
    p = pairs[name]
    for truth, labels in ((p.truth_appeared, p.current_labels),
                          (p.truth_disappeared, p.reference_labels)):
        assert truth.sum() > 1000
        ids = labels // 10
        share = sorted((truth & (ids == i)).sum() / truth.sum()
                       for i in np.unique(ids[labels >= 20]))
        assert share[-1] >= 0.95
        fractions = sorted(object_fractions(truth, labels).values())
        assert all(f <= 0.02 for f in fractions[:-1])


def test_everything_moved(pairs):
    """test36 -> test37 (all 3 moved): every current object >= 50 % appeared; learn38 ->
    learn39 (all 4 rearranged): every reference object >= 25 % disappeared."""
    p = pairs["test36-test37"]
    fractions = object_fractions(p.truth_appeared, p.current_labels)
    assert len(fractions) == 3 and min(fractions.values()) >= 0.5
    p = pairs["learn38-learn39"]
    fractions = object_fractions(p.truth_disappeared, p.reference_labels)
    assert len(fractions) == 4 and min(fractions.values()) >= 0.25


def test_cup_removed_and_others_kept(pairs):
    """learn39 -> learn40 (4 -> 3 objects, a cup removed): one reference object >= 90 %
    disappeared, one (the unmoved right-hand one) <= 1 %."""
    p = pairs["learn39-learn40"]
    fractions = object_fractions(p.truth_disappeared, p.reference_labels)
    assert len(fractions) == 4
    assert max(fractions.values()) >= 0.9 and min(fractions.values()) <= 0.01


def test_stacked_pot_and_tin(pairs):
    """learn40 -> learn41: pot and tin leave their places (>= 70 % disappeared each), the new
    stack is >= 80 % appeared; the removed cup is hidden behind the stack (no truth)."""
    p = pairs["learn40-learn41"]
    disappeared = sorted(object_fractions(p.truth_disappeared, p.reference_labels).values())
    assert disappeared[0] == 0.0 and min(disappeared[1:]) >= 0.7
    appeared = object_fractions(p.truth_appeared, p.current_labels)
    assert len(appeared) == 2 and min(appeared.values()) >= 0.8


def test_changed_objects_are_the_readme_ones(pairs):
    """The changed objects whole: test9 -> test10 the rear box only (its edge touches the
    front box's, whose 9 truth pixels lie on that edge); test37 -> test38 the tin only;
    learn39 -> learn40 three of the four reference objects (a cup removed, another swapped,
    the tin shifted: 31-94 % truth), not the unmoved right-hand one."""
    def ids(labels, truth):
        mask = changed_objects(labels, truth)
        return sorted(set((labels[mask] // 10).tolist()))

    p = pairs["test9-test10"]
    fractions = object_fractions(p.truth_appeared, p.current_labels)
    front = min(fractions, key=fractions.get)
    assert 0 < fractions[front] < 0.01  # the front box's edge is touched
    assert ids(p.current_labels, p.truth_appeared) == [max(fractions, key=fractions.get)]
    assert ids(p.reference_labels, p.truth_disappeared) == [3]
    p = pairs["test37-test38"]
    assert len(ids(p.current_labels, p.truth_appeared)) == 1
    p = pairs["learn39-learn40"]
    assert ids(p.reference_labels, p.truth_disappeared) == [2, 3, 4]
    for p in pairs.values():
        for labels, truth in ((p.current_labels, p.truth_appeared),
                              (p.reference_labels, p.truth_disappeared)):
            mask = changed_objects(labels, truth)
            assert not (mask & (labels < 20)).any()
            assert truth[mask].sum() >= truth.sum() * 0.95  # a changed object's truth is kept


# ---- the rule on small synthetic images ------------------------------------------------------

def test_changed_objects_whole_and_not_by_an_edge():
    """An object with truth well inside is changed whole, every part of it; one whose truth
    lies only along its edge (a neighbour's change touching it) is not; below min_px inside is
    not either."""
    labels = np.full((40, 60), TABLE, np.uint16)
    labels[5:25, 5:25] = OBJ_A                  # touched along its right edge only
    labels[5:25, 30:40] = OBJ_B                 # object 3, part 0
    labels[5:25, 40:50] = OBJ_B + 1             # object 3, part 1
    truth = np.zeros(labels.shape, bool)
    truth[5:25, 25 - OBJECT_EDGE_PX:25] = True  # 60 px, all within the edge band of OBJ_A
    truth[10:20, 32:37] = True                  # 50 px inside object 3's part 0
    mask = changed_objects(labels, truth)
    assert mask[5:25, 30:50].all() and not mask[labels < OBJ_B].any()
    assert not changed_objects(labels, truth, min_px=51).any()
    assert changed_objects(labels, truth, edge_px=0)[5:25, 5:25].all()



def scene(h=40, w=60, table_mm=1000):
    """(depth uint16 mm, labels uint16): a flat table filling the image."""
    return np.full((h, w), table_mm, np.uint16), np.full((h, w), TABLE, np.uint16)


def test_rule_added_object_and_its_margin():
    ref, ref_lab = scene()
    cur, cur_lab = scene()
    cur[10:20, 10:20], cur_lab[10:20, 10:20] = 1000 - TRUTH_MARGIN_MM - 1, OBJ_A   # new, in front
    cur[10:20, 30:40], cur_lab[10:20, 30:40] = 1000 - TRUTH_MARGIN_MM, OBJ_B       # at the margin
    appeared, disappeared = tabletop_truth(ref, ref_lab, cur, cur_lab)
    expected = np.zeros_like(appeared)
    expected[10:20, 10:20] = True
    assert np.array_equal(appeared, expected)
    assert not disappeared.any()
    # swapped epochs: the object disappeared
    appeared2, disappeared2 = tabletop_truth(cur, cur_lab, ref, ref_lab)
    assert np.array_equal(disappeared2, expected) and not appeared2.any()


def test_rule_static_object_and_uncovered_table_are_not_truth():
    ref, ref_lab = scene()
    ref[10:20, 10:20], ref_lab[10:20, 10:20] = 800, OBJ_A
    cur, cur_lab = ref.copy(), ref_lab.copy()
    cur[10:20, 10:20] += 15                                   # noise within the margin
    appeared, disappeared = tabletop_truth(ref, ref_lab, cur, cur_lab)
    assert not appeared.any() and not disappeared.any()
    # the object removed: its pixels are disappeared; the uncovered table is not "appeared"
    appeared, disappeared = tabletop_truth(ref, ref_lab, *scene())
    assert disappeared.sum() == 100 and not appeared.any()


def test_rule_dropout_under_a_static_object_is_not_truth():
    ref, ref_lab = scene()
    ref[5:35, 5:35], ref_lab[5:35, 5:35] = 800, OBJ_A
    cur, cur_lab = ref.copy(), ref_lab.copy()
    ref[12:20, 12:20] = ref_lab[12:20, 12:20] = 0             # dropout in the reference...
    ref[5:30, 34] = ref_lab[5:30, 34] = 0                     # ...and one at the object's edge
    appeared, disappeared = tabletop_truth(ref, ref_lab, cur, cur_lab)
    assert not appeared.any() and not disappeared.any()
    # but a new object over a reference hole surrounded by table is appeared
    ref2, ref_lab2 = scene()
    ref2[12:20, 40:50] = ref_lab2[12:20, 40:50] = 0
    cur2, cur_lab2 = scene()
    cur2[10:22, 38:52], cur_lab2[10:22, 38:52] = 900, OBJ_A
    appeared, _ = tabletop_truth(ref2, ref_lab2, cur2, cur_lab2)
    assert appeared.sum() == 12 * 14


def test_rule_crop_difference_is_not_truth():
    ref, ref_lab = scene()
    ref[:, 45:] = ref_lab[:, 45:] = 0                         # cropped at the right edge
    cur, cur_lab = scene()
    cur[10:20, 40:55], cur_lab[10:20, 40:55] = 900, OBJ_A     # object across the crop edge
    appeared, _ = tabletop_truth(ref, ref_lab, cur, cur_lab)
    expected = np.zeros_like(appeared)
    expected[10:20, 40:45] = True
    assert np.array_equal(appeared, expected)
    assert not footprint(ref)[:, 45:].any() and footprint(ref)[:, :45].all()


def test_rule_drops_specks():
    ref, ref_lab = scene()
    cur, cur_lab = scene()
    cur[5:10, 5:8], cur_lab[5:10, 5:8] = 900, OBJ_A           # 15 px < MIN_REGION_PX
    cur[20:25, 20:25], cur_lab[20:25, 20:25] = 900, OBJ_B     # 25 px
    appeared, _ = tabletop_truth(ref, ref_lab, cur, cur_lab)
    assert appeared.sum() == 25 and not appeared[5:10, 5:8].any()
    appeared, _ = tabletop_truth(ref, ref_lab, cur, cur_lab, min_region_px=0)
    assert appeared.sum() == 40
    mask = np.zeros((10, 10), bool)
    mask[0, 0] = mask[5:9, 5:9] = True
    assert drop_specks(mask, 2).sum() == 16 and drop_specks(mask, 17).sum() == 0


def test_rule_rejects_mismatched_shapes():
    ref, lab = scene()
    with pytest.raises(ValueError, match="shape"):
        tabletop_truth(ref, lab, ref[:-1], lab[:-1])


def test_fill_dropouts_grows_the_nearest_surface_inward():
    depth = np.full((9, 9), 1000, np.uint16)
    depth[:, :3] = 700
    depth[3:6, 2:6] = 0                                      # a hole touching both surfaces
    depth[0, 8] = 0                                          # on the border: outside footprint
    filled = fill_dropouts(depth)
    assert filled.dtype == np.int32
    # ring by ring from the hole's edge, each pixel the nearest depth of its 3x3 neighbours
    assert filled[3:6, 2:6].tolist() == [[700, 700, 1000, 1000],
                                         [700, 700, 700, 1000],
                                         [700, 700, 1000, 1000]]
    assert filled[0, 8] == 0
    assert np.array_equal(filled[depth > 0], depth[depth > 0])


# ---- errors ----------------------------------------------------------------------------------

def test_unknown_name_lists_the_known_pairs(tmp_path):
    with pytest.raises(UnknownScene) as info:
        load_tabletop_pair("test1-test2", tmp_path)
    assert isinstance(info.value, KeyError)
    for name in README_PAIRS:
        assert name in str(info.value)


def test_missing_data_folder(tmp_path):
    with pytest.raises(TabletopDataMissing, match="table-top data not found") as info:
        load_tabletop_pair("test9-test10", tmp_path / "nowhere")
    assert isinstance(info.value, FileNotFoundError)
    assert str(tmp_path / "nowhere") in str(info.value)


def test_missing_image_in_the_data_folder(tmp_path):
    (tmp_path / "derived").mkdir()
    with pytest.raises(TabletopDataMissing, match="test9_depth_mm.png"):
        load_tabletop_pair("test9-test10", tmp_path)
