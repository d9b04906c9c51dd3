"""Conformance with the authors' model (issue 13): folders written in their conventions by an
independent NumPy generator (``tests/acm_conformance.py``) must be read, posed, projected and
learned exactly as the authors' tool would."""

from __future__ import annotations

import acm_conformance as ac
import numpy as np
import pytest

import acm_rs
from acm_rs import acm_formats as af
from acm_rs.calibration import load_acm_calibration
from acm_rs.learning import learn_skeleton


def _read(folder):
    cfg = af.read_configuration(folder / "configuration.py")
    model = af.read_model(folder / "model.npy", species=cfg.species)
    rig = load_acm_calibration(
        folder / "multicalibration.npy", folder / "origin_coord.npy",
        scale_factor=cfg.scale_factor, image_size=(1280, 1024),
    )  # fmt: skip
    return cfg, model, rig


def _truth_skeleton(c: ac.Conformance, model: af.AcmModel) -> acm_rs.Skeleton:
    sk = model.skeleton
    lengths = np.array([c.bone_lengths[n] for n in sk.bone_names])
    offsets = np.array([c.marker_offsets[n] for n in sk.marker_names])
    return sk.with_parameters(lengths, offsets)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return ac.write_conformance_dataset(
        tmp_path_factory.mktemp("conf"), seed=2, n_manual=30, n_dlc=120, full_distortion=True
    )


@pytest.mark.parametrize("links", ["tree", "literal"])
def test_forward_model_is_the_authors(folder, links, tmp_path):
    """Our FK of the skeleton read from model.npy = the authors' adjust_joint_marker_pos2,
    for the links of the authors' files (tree) and for the literal Alg. 1 links."""
    if links != "tree":
        folder = ac.write_conformance_dataset(tmp_path, seed=2, n_manual=4, n_dlc=4, links=links)
    _, model, _ = _read(folder.folder)
    assert model.links_rule == {"tree": "tree", "literal": "literal Alg. 1"}[links]
    truth = _truth_skeleton(folder, model)
    am = ac.AuthorsModel(np.random.default_rng(2), links)  # the geometry written for seed 2
    rng = np.random.default_rng(7)
    t, r = ac._poses(am, rng, 6, smooth=False)
    lengths = np.array([folder.bone_lengths[e] for _, e in am.bones])
    ours_r = np.zeros((len(t), truth.n_bones, 3))
    for b, (_, e) in enumerate(am.bones):
        ours_r[:, truth.bone_index(e)] = r[:, b]
    for f in range(len(t)):
        joints, markers = am.forward(t[f], r[f], lengths, folder.marker_offsets)
        oj, om = truth.forward(t[f], ours_r[f])
        for n, p in joints.items():
            np.testing.assert_allclose(oj[truth.joint_index(n)], p, atol=1e-10)
        for n, p in markers.items():
            np.testing.assert_allclose(om[truth.marker_index(n)], p, atol=1e-10)
    # the two rules really differ on these poses (the girdles against the spine)
    other = ac.AuthorsModel(np.random.default_rng(2), "literal" if links == "tree" else "tree")
    j_other, _ = other.forward(t[1], r[1], lengths, folder.marker_offsets)
    j_this, _ = am.forward(t[1], r[1], lengths, folder.marker_offsets)
    assert max(np.linalg.norm(j_other[n] - j_this[n]) for n in j_this) > 0.1


def test_projection_is_the_authors(folder):
    """The rig read from multicalibration.npy + origin_coord.npy projects as model.map_m."""
    _, _, rig = _read(folder.folder)
    cal = np.load(folder.folder / "multicalibration.npy", allow_pickle=True).item()
    oc = np.load(folder.folder / "origin_coord.npy", allow_pickle=True).item()
    assert np.any(cal["k_fit"][:, 2:] != 0)  # tangential and k3 exercised
    rot = np.einsum("nij,jk->nik", cal["RX1_fit"], oc["coord"])
    tvec = (cal["tX1_fit"] + np.einsum("nij,j->ni", cal["RX1_fit"], oc["origin"])) * 6.5
    pts = np.random.default_rng(1).normal(scale=8.0, size=(60, 3)) + [0.0, 0.0, 5.0]
    expected = ac.authors_project(cal["A_fit"], cal["k_fit"], rot, tvec, pts)
    ours = np.array([cam.project(pts) for cam in rig])
    np.testing.assert_allclose(ours, expected, atol=1e-6)


def test_learning_is_exact_on_noise_free_labels(tmp_path):
    """Without label noise (and without the length prior, which would bias it) the learned
    bones and offsets are the truth (to 1e-6 cm), from the generic model and a 350 g animal
    (the size is found from the labels)."""
    c = ac.write_conformance_dataset(tmp_path, seed=0, body_weight=350.0, manual_noise=0.0)
    cfg, model, rig = _read(c.folder)
    manual = af.read_labels_manual(
        c.folder / "labels_manual.npz", model.acm_marker_names, n_cams=len(rig)
    )
    learned = learn_skeleton(
        rig, model.skeleton, manual.points, body_weight=cfg.body_weight,
        marker_names=manual.marker_names, progress=False, length_prior_sd=None,
    )  # fmt: skip
    truth = _truth_skeleton(c, model)
    assert learned.rms < 1e-4
    np.testing.assert_allclose(learned.skeleton.bone_lengths, truth.bone_lengths, atol=1e-6)
    np.testing.assert_allclose(learned.skeleton.marker_offsets, truth.marker_offsets, atol=1e-5)
    assert learned.info["size_scale"] > 1.5  # the generic model is a ~72 g rat


@pytest.mark.parametrize("weight", [72.0, 350.0])
def test_run_acm_recovers_the_individual(tmp_path, weight):
    """run-acm on a folder in the authors' conventions (30 manual frames at 1 px, 2 px DLC
    labels with 10 % dropouts): bones and joints at the accuracy the issue asks for."""
    from acm_rs.run_acm import run_acm

    c = ac.write_conformance_dataset(tmp_path / "data", seed=2, body_weight=weight, n_manual=30)
    res = run_acm(c.folder, tmp_path / "out", progress=False)
    sk = res.learned.skeleton
    err = np.array([sk.bone_lengths[sk.bone_index(n)] - v for n, v in c.bone_lengths.items()])
    # one folder each; the target (mean 0.05 cm, joints 0.08 cm) is over many folders
    # (benches/acm_conformance.py: 24 folders, see benches/README.md)
    assert np.abs(err).mean() < 0.06, err  # cm
    assert res.learned.rms < 1.5  # 1 px label noise: ~1.3 px RMS of the 2D error
    pose = np.load(tmp_path / "out" / "pose.npy", allow_pickle=True).item()
    idx = np.searchsorted(c.frames, res.result.info["frames"])
    joint_err = np.linalg.norm(pose["joint_positions_3d"] - c.joints[idx], axis=-1)
    assert joint_err.mean() < 0.09  # cm
    d = res.learned.diagnostics()
    assert not d["bones_on_bounds"] and not d["off_proportions"]
    assert 0.8 < d["noise_px"] < 1.3  # labels carry 1 px per coordinate


def test_bundled_rat_has_the_authors_facts():
    """The bundled rat's limits, marker boxes and bone-length priors equal the tables written
    from the authors' anatomy.py (tests/acm_conformance.py), including the right hip's
    y-range [-25, 65] deg (the paper's table prints [25, 65]) and no metacarpal prior."""
    rat = acm_rs.models.rat()
    names = rat.joint_names
    parent = {n: names[p] if p >= 0 else "" for n, p in zip(names, rat.parents, strict=True)}
    for b, name in enumerate(rat.bone_names):
        start = parent[name]
        if b == 0:
            expected = np.full((3, 2), [-np.inf, np.inf])
        elif name in ac.GIRDLES:
            expected = np.zeros((3, 2))
        else:
            expected = np.radians(np.array(ac.LIMITS_BY_START.get(start, ac.SPINE_LIMITS), float))
        np.testing.assert_allclose(rat.joint_limits[b], expected, atol=1e-12, err_msg=name)
    for name, box in ac.MARKER_BOXES.items():
        np.testing.assert_array_equal(rat.marker_bounds[rat.marker_index(name)], box, name)
    priors = {c.bone: (c.slope, c.slope_sd) for c in rat.bone_length_constraints}
    expected = {f"{base}_{side}": v for base, v in ac.PRIORS.items() for side in ("left", "right")}
    assert priors == expected
    for marker, joint in ac.MARKERS.items():
        assert rat.joint_names[rat.marker_joints[rat.marker_index(marker)]] == joint


def test_diagnostics_name_bounds_outliers_and_wrong_weights(tmp_path):
    """A body weight too small for the animal pins the limb bones on their priors; a label
    moved by 60 px stands out; both are named in the summary. Kilograms are refused."""
    from acm_rs.learning import check_body_weight

    c = ac.write_conformance_dataset(tmp_path, seed=1, body_weight=72.0, n_manual=25)
    cfg, model, rig = _read(c.folder)
    manual = af.read_labels_manual(
        c.folder / "labels_manual.npz", model.acm_marker_names, n_cams=len(rig)
    )
    points = manual.points.copy()
    k = manual.marker_names.index("knee_left")
    f = int(np.flatnonzero(np.isfinite(points[0, :, k, 0]))[0])
    points[0, f, k] += 60.0
    with pytest.warns(UserWarning, match="outside their priors"):
        learned = learn_skeleton(
            rig, model.skeleton, points, body_weight=30.0, marker_names=manual.marker_names,
            progress=False,
        )  # fmt: skip
    d = learned.diagnostics()
    pinned = {b for b, _, _ in d["bones_on_bounds"]}
    assert {"elbow_left", "knee_left"} <= pinned  # humerus, femur at their upper bounds
    assert (rig.names[0] or "0", f, "knee_left") == d["outliers"][0][:3]
    assert d["outliers"][0][3] > 30.0
    text = learned.summary()
    assert "WARNING bones on a bound" in text and "knee_left in" in text
    assert "outside" in text  # the generic model vs the priors at 30 g
    # the right weight: nothing on a bound
    assert check_body_weight(model.skeleton, 72.0) == []
    with pytest.raises(ValueError, match="give grams"):
        check_body_weight(model.skeleton, 0.35)


def test_units_and_likelihood_are_honoured(tmp_path):
    """A model in mm learns the same skeleton (x 10); a rig in mm with the model in cm is
    refused with a message naming the units; prediction labels below pcutoff are not used
    and likelihoods on a 0-100 scale are refused."""
    c = ac.write_conformance_dataset(tmp_path, seed=3, body_weight=72.0, n_manual=20)
    cfg, model, rig = _read(c.folder)
    manual = af.read_labels_manual(
        c.folder / "labels_manual.npz", model.acm_marker_names, n_cams=len(rig)
    )
    kw = dict(body_weight=72.0, marker_names=manual.marker_names, progress=False)
    ref = learn_skeleton(rig, model.skeleton, manual.points, **kw)
    # the same in mm
    sk_mm = acm_rs.Skeleton.from_dict(model.skeleton.to_dict() | {"units": "mm"})
    sk_mm = sk_mm.with_parameters(sk_mm.bone_lengths * 10, sk_mm.marker_offsets * 10)
    mm_constraints = [
        type(b)(bone=b.bone, slope=b.slope * 10, slope_sd=b.slope_sd * 10)
        for b in sk_mm.bone_length_constraints
    ]
    doc = sk_mm.to_dict() | {"bone_length_constraints": [vars(b) for b in mm_constraints]}
    sk_mm = acm_rs.Skeleton.from_dict(doc)
    in_mm = learn_skeleton(rig.scaled(10.0), sk_mm, manual.points, **kw)
    np.testing.assert_allclose(in_mm.skeleton.bone_lengths / 10, ref.skeleton.bone_lengths,
                               rtol=2e-3, atol=2e-3)  # fmt: skip
    assert abs(in_mm.rms - ref.rms) < 0.01
    # mixing: rig in mm, model in cm
    with pytest.raises(ValueError, match=r"calibration in mm while the model is in cm"):
        learn_skeleton(rig.scaled(10.0), model.skeleton, manual.points, **kw)
    # predictions: confident mistakes below pcutoff are dropped
    pts = manual.points.copy()
    lik = np.full(pts.shape[:-1], 0.99)
    bad = np.random.default_rng(0).random(lik.shape) < 0.1
    pts[bad] += 80.0
    lik[bad] = 0.3
    pred = learn_skeleton(rig, model.skeleton, pts, likelihood=lik, pcutoff=0.9, **kw)
    assert pred.rms < 1.5
    with pytest.raises(ValueError, match="0-100 scale"):
        learn_skeleton(rig, model.skeleton, pts, likelihood=lik * 100, **kw)
    with pytest.raises(ValueError, match="unknown length unit 'inches'"):
        acm_rs.Normalization.for_units("inches")
