"""Training data: the cache, the non-finite policy, aligned crops and consistent augmentations."""
import json

import numpy as np
import pytest

from gbuffer_export import demod as np_demod
from gbuffer_export.clip import open_clip
from gbuffer_export.conventions import backward_warp, reprojection_motion, world_to_camera_normals
from gbuffer_export.exr import write_exr
from gbuffer_export.synthetic import make_synthetic_clip, trace
from training.augment import Augmentation, apply
from training.cache import ClipCache, NonFiniteError



@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("clip") / "c", frames=range(1, 6), hr_size=(128, 72), scale=4)


def test_cache_stores_every_buffer_once_with_declared_dtypes(clip, tmp_path):
    cache = ClipCache(clip, cache_dir=tmp_path)
    keys = ["lr/radiance", "hr/radiance", "hr/normal", "lr/depth", "lr/motion", "hr/flags", "lr/irradiance",
            "hr/fbeta_used"]
    cache.ensure(keys)
    c = open_clip(clip)
    assert cache.array("hr/radiance").dtype == np.float32 and cache.array("hr/normal").dtype == np.float16
    assert cache.array("lr/motion").dtype == np.float32 and cache.array("hr/flags").dtype == np.uint32
    assert cache.array("hr/radiance").shape == (5, 72, 128, 3)
    for f in (1, 5):
        np.testing.assert_array_equal(cache.read(f, "hr/radiance"), c.read(f, "hr/radiance"))
        np.testing.assert_array_equal(cache.read(f, "lr/depth"), c.read(f, "lr/depth"))  # +inf kept
        np.testing.assert_allclose(cache.read(f, "hr/normal"), c.read(f, "hr/normal"), atol=1e-3)
        irr, fbu = np_demod.demodulate(c.read(f, "lr/radiance"), c.read(f, "lr/emission"), c.read(f, "lr/fbeta"),
                                       c.read(f, "lr/flags"), 0.01)
        np.testing.assert_array_equal(cache.read(f, "lr/irradiance"), irr)
        d = c.read(f, "lr/depth")[..., 0]
        assert cache.depth_ref(f) == pytest.approx(float(np.median(d[np.isfinite(d)])))
    assert np.isinf(cache.read(1, "lr/depth")).any()
    # Opening again reuses the arrays
    again = ClipCache(clip, cache_dir=tmp_path)
    assert not again.rebuilt and set(keys) <= set(again.index["arrays"])


def test_cache_rebuilds_when_the_manifest_changes(tmp_path):
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 3), hr_size=(64, 36), scale=4)
    cache = ClipCache(clip).ensure(["lr/radiance"])
    assert cache.path == clip / ".blendsr_cache"
    old = cache.read(2, "lr/radiance")
    # Re-render frame 2 brighter and change its record: the manifest hash changes.
    c = open_clip(clip)
    write_exr(c.path_of(2, "lr/radiance"), {ch: 2 * old[..., i] for i, ch in enumerate("RGB")})
    m = json.loads((clip / "manifest.json").read_text())
    m["frame_data"]["2"]["lr"]["spp"] = 8
    (clip / "manifest.json").write_text(json.dumps(m))
    fresh = ClipCache(clip)
    assert fresh.rebuilt and fresh.index["arrays"] == {}
    fresh.ensure(["lr/radiance"])
    np.testing.assert_array_equal(fresh.read(2, "lr/radiance"), 2 * old)
    # Same manifest, different eps: rebuilt too (irradiance depends on it)
    assert ClipCache(clip, eps=0.02).rebuilt


def _poison(clip, frame, key):
    c = open_clip(clip)
    a = c.read(frame, key)
    a[3, 4, 1] = np.nan
    a[0, 0, 0] = np.inf
    write_exr(c.path_of(frame, key), {ch: a[..., i] for i, ch in enumerate("RGB")})
    return c.path_of(frame, key)


def test_nonfinite_input_is_an_error_naming_file_and_frame(tmp_path):
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(64, 36), scale=4)
    path = _poison(clip, 2, "lr/radiance")
    with pytest.raises(NonFiniteError) as err:
        ClipCache(clip).ensure(["lr/radiance"])
    msg = str(err.value)
    assert str(path) in msg and "frame 2" in msg and "sanitize" in msg
    assert "lr/radiance: 2 of 144 pixel(s) non-finite (1 NaN, 1 Inf) [non-finite]" in msg  # validate's words


def test_nonfinite_input_sanitised_with_a_warning(tmp_path):
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(64, 36), scale=4)
    _poison(clip, 2, "lr/radiance")
    with pytest.warns(RuntimeWarning, match="frame 2"):
        cache = ClipCache(clip, nonfinite="sanitize").ensure(["lr/radiance", "lr/irradiance"])
    a = cache.read(2, "lr/radiance")
    assert a[3, 4, 1] == 0.0 and a[0, 0, 0] == np_demod.RADIANCE_CAP
    assert np.isfinite(cache.read(2, "lr/irradiance")).all()
    assert cache.index["sanitized"][0]["count"] == 2


def test_crops_are_aligned_across_levels_and_windows_are_consecutive(clip, tmp_path):
    from training.data import BatchSpec, TrainSampler
    cache = ClipCache(clip, cache_dir=tmp_path)
    spec = BatchSpec(lr_keys=("lr/radiance", "lr/motion"), hr_keys=("hr/radiance", "hr/depth"), lr_window=3,
                     hr_window=2, crop=8, depth_ref=True)
    cache.ensure(spec.cache_keys)
    sampler = TrainSampler([cache], spec, batch_size=4, seed=7)
    batch, samples = sampler.batch(3)
    c = open_clip(clip)
    assert batch["lr/radiance"].shape == (4, 3, 3, 8, 8) and batch["hr/radiance"].shape == (4, 2, 3, 32, 32)
    for b, s in enumerate(samples):
        assert s.frames == list(range(s.frames[0], s.frames[0] + 3))
        for t, f in enumerate(s.frames):
            lr = c.read(f, "lr/radiance")[s.y0:s.y0 + 8, s.x0:s.x0 + 8]
            np.testing.assert_array_equal(batch["lr/radiance"][b, t], apply("lr/radiance", lr, s.aug).transpose(2, 0, 1))
            assert batch["depth_ref"][b, t] == pytest.approx(cache.depth_ref(f))
        for t, f in enumerate(s.frames[-2:]):
            hr = c.read(f, "hr/radiance")[4 * s.y0:4 * s.y0 + 32, 4 * s.x0:4 * s.x0 + 32]
            np.testing.assert_array_equal(batch["hr/radiance"][b, t], hr.transpose(2, 0, 1))
    # Same step, same batch (resume relies on it); another step differs.
    again, _ = TrainSampler([cache], spec, batch_size=4, seed=7).batch(3)
    np.testing.assert_array_equal(again["hr/radiance"], batch["hr/radiance"])
    assert not np.array_equal(sampler.batch(4)[0]["hr/radiance"], batch["hr/radiance"])


AUGS = [Augmentation(transpose=True), Augmentation(flip_x=True), Augmentation(flip_y=True),
        Augmentation(transpose=True, flip_x=True), Augmentation(transpose=True, flip_x=True, flip_y=True)]


def _camera_map(aug):
    """3x3 M with camera'-space = M camera-space for the augmented image (see training.augment)."""
    m = np.eye(3)
    if aug.transpose:
        m = np.array([[0, -1, 0], [-1, 0, 0], [0, 0, 1.0]]) @ m
    if aug.flip_x:
        m = np.diag([-1.0, 1, 1]) @ m
    if aug.flip_y:
        m = np.diag([1.0, -1, 1]) @ m
    return m


def mirrored_camera(c, frame: int, level: str, aug):
    """The camera that sees the augmented image of ``level``: (camera dict, world_from_camera, previous
    world_from_camera, (width, height), intrinsics)."""
    w, h = c.sizes[level]
    cam = c.camera(frame, level)
    m4 = np.eye(4)
    m4[:3, :3] = np.linalg.inv(_camera_map(aug))
    w2, h2 = (h, w) if aug.transpose else (w, h)
    fx = cam["intrinsics"][0]
    return (cam, cam["world_from_camera"] @ m4, cam["prev_world_from_camera"] @ m4, (w2, h2),
            (fx, fx, w2 / 2, h2 / 2))


@pytest.mark.parametrize("aug", AUGS, ids=str)
def test_augmented_gbuffers_equal_a_render_by_the_mirrored_camera(clip, aug):
    """Independent check of the normal and motion transforms: render the scene with the camera that sees the
    augmented image (a mirrored/rotated pinhole) and compare."""
    c = open_clip(clip)
    f = 3
    _, wfc, wfc_prev, (w2, h2), k2 = mirrored_camera(c, f, "hr", aug)
    g = trace(w2, h2, k2, wfc)
    normal_ref = world_to_camera_normals(g["normal_world"], wfc)
    motion_ref = reprojection_motion(g["depth"], k2, wfc, k2, wfc_prev)
    depth_aug = apply("hr/depth", c.read(f, "hr/depth"), aug)[..., 0]
    normal_aug = apply("hr/normal", c.read(f, "hr/normal"), aug)
    motion_aug = apply("hr/motion", c.read(f, "hr/motion"), aug)
    assert depth_aug.shape == (h2, w2)
    both = np.isfinite(depth_aug) & np.isfinite(g["depth"])
    da, dr = np.where(both, depth_aug, 1.0), np.where(both, g["depth"], 1.0)
    same = both & (np.abs(da - dr) <= 1e-4 * dr)
    assert same.sum() >= 0.995 * both.sum() and both.sum() > 0.5 * both.size
    np.testing.assert_allclose(normal_aug[same], normal_ref[same], atol=1e-5)
    np.testing.assert_allclose(motion_aug[same], motion_ref[same], atol=2e-3)
    assert np.abs(motion_ref[same]).max() > 0.5  # the camera moves: a sign error would show


@pytest.mark.parametrize("aug", AUGS + [Augmentation(exposure=1.7)], ids=str)
def test_warping_an_augmented_frame_with_its_augmented_motion(clip, aug):
    c = open_clip(clip)
    prev, cur, motion = c.read(2, "hr/radiance"), c.read(3, "hr/radiance"), c.read(3, "hr/motion")
    warped, valid = backward_warp(apply("hr/radiance", prev, aug), apply("hr/motion", motion, aug))
    ref, ref_valid = backward_warp(prev, motion)
    np.testing.assert_array_equal(valid, apply("x/flags", ref_valid[..., None], aug)[..., 0])
    np.testing.assert_allclose(warped, apply("hr/radiance", ref, aug), rtol=1e-5, atol=1e-5)
    # and the warp explains the augmented current frame far better than un-transformed motion does
    cur_a = apply("hr/radiance", cur, aug)
    err = np.median(np.abs(warped - cur_a)[valid])  # median: edges of the textured scene blur under warping
    wrong, wv = backward_warp(apply("hr/radiance", prev, aug), apply("x/none", motion, aug))
    if aug.transpose or aug.flip_x or aug.flip_y:
        assert err < 0.6 * np.median(np.abs(wrong - cur_a)[wv])
    no_motion = np.median(np.abs(apply("hr/radiance", prev, aug) - cur_a)[valid])
    assert err < 0.4 * no_motion


def test_exposure_keeps_the_demodulation_identity(clip):
    c = open_clip(clip)
    aug = Augmentation(exposure=0.6, flip_x=True)
    rad = apply("hr/radiance", c.read(2, "hr/radiance"), aug)
    em = apply("hr/emission", c.read(2, "hr/emission"), aug)
    fb = apply("hr/fbeta", c.read(2, "hr/fbeta"), aug)
    irr, fbu = np_demod.demodulate(c.read(2, "hr/radiance"), c.read(2, "hr/emission"), c.read(2, "hr/fbeta"),
                                   c.read(2, "hr/flags"))
    irr_a = apply("hr/irradiance", irr, aug)
    np.testing.assert_allclose(irr_a * apply("hr/fbeta_used", fbu, aug) + em, rad, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(fb, np.flip(c.read(2, "hr/fbeta"), axis=1))


def test_reflectance_keeps_the_demodulation_identity_and_the_irradiance(clip):
    """A tinted BRDF under the same light: the augmented buffers satisfy I = L_D * F_used + E, the irradiance the
    model predicts is unchanged, and demodulating the augmented raw buffers gives it back (independently of
    ``apply``'s list of buffers) wherever F_beta is trusted and not clamped."""
    c = open_clip(clip)
    tint = (0.6, 1.3, 1.9)
    aug = Augmentation(reflectance=tint, flip_y=True)
    raw = {k: c.read(2, f"hr/{k}") for k in ("radiance", "emission", "fbeta", "albedo", "flags")}
    irr, fbu = np_demod.demodulate(raw["radiance"], raw["emission"], raw["fbeta"], raw["flags"])
    unit = (fbu == 1.0).all(-1, keepdims=True)  # background / UNTRUSTED: F_used = 1, L_D = I - E
    assert unit.any() and not unit.all()
    with pytest.raises(ValueError, match="needs the F_used = 1 mask"):
        apply("hr/irradiance", irr, aug)
    a = {k: apply(f"hr/{k}", v, aug, unit) for k, v in {**raw, "irradiance": irr, "fbeta_used": fbu}.items()}
    np.testing.assert_allclose(a["irradiance"] * a["fbeta_used"] + a["emission"], a["radiance"], rtol=1e-5, atol=1e-6)
    flipped_unit = np.flip(unit, axis=0)
    np.testing.assert_array_equal(np.where(flipped_unit, 0, a["irradiance"]), np.where(flipped_unit, 0, np.flip(irr, 0)))
    np.testing.assert_array_equal((a["fbeta_used"] == 1.0).all(-1, keepdims=True), flipped_unit)  # the class stays
    np.testing.assert_allclose(a["irradiance"][flipped_unit[..., 0]],
                               (np.flip(irr, 0) * np.float32(tint))[flipped_unit[..., 0]], rtol=1e-6)
    np.testing.assert_allclose(a["albedo"], np.flip(raw["albedo"], axis=0) * np.float32(tint), rtol=1e-6)
    np.testing.assert_array_equal(a["flags"], np.flip(raw["flags"], axis=0))
    irr_again, _ = np_demod.demodulate(a["radiance"], a["emission"], a["fbeta"], a["flags"])
    # pixels demodulated by F_beta itself (not 1) where the tinted F_beta (>= 0.6 F_beta) stays above the eps clamp
    trusted = (fbu != 1.0).all(-1) & (raw["fbeta"] > 0.05).all(-1)
    trusted = np.flip(trusted, 0)  # into the augmented (flipped) image
    assert trusted.mean() > 0.3
    np.testing.assert_allclose(irr_again[trusted], a["irradiance"][trusted], rtol=1e-4, atol=1e-6)
    # and where F_used = 1: L_D = tinted I - tinted E
    np.testing.assert_allclose(irr_again[flipped_unit[..., 0]], a["irradiance"][flipped_unit[..., 0]], rtol=1e-5,
                               atol=1e-6)


def test_draw_uses_a_fixed_number_of_variates():
    a = np.random.default_rng(1)
    b = np.random.default_rng(1)
    Augmentation.draw(a, True, True, (0.5, 2), (0.5, 2))
    Augmentation.draw(b, False, False)
    assert a.random() == b.random()


def test_draw_tints_each_channel_log_uniformly_within_the_range():
    rng = np.random.default_rng(3)
    tints = np.array([Augmentation.draw(rng, True, True, (1, 1), (0.5, 2.0)).reflectance for _ in range(2000)])
    assert tints.min() >= 0.5 and tints.max() <= 2.0
    logs = np.log2(tints)
    np.testing.assert_allclose(logs.mean(0), 0.0, atol=0.05)  # log-uniform on [-1, 1]: mean 0, variance 1/3
    np.testing.assert_allclose(logs.var(0), 1 / 3, atol=0.03)
    assert abs(np.corrcoef(logs.T)[0, 1]) < 0.1  # channels drawn independently
    assert Augmentation.draw(rng, True, True).reflectance == (1.0, 1.0, 1.0)


def test_tinted_batches_keep_unit_fbeta_where_the_clip_has_it(clip, tmp_path):
    """Under the reflectance tint a batch's F_used is exactly 1 where the clip's is (the class models.base's
    demodulated_mask reads), the other pixels are tinted, and I = F_used L_D + E still holds."""
    from training.data import BatchSpec, TrainSampler
    cache = ClipCache(clip, cache_dir=tmp_path)
    keys = ("lr/radiance", "lr/emission", "lr/irradiance", "lr/fbeta_used")
    spec = BatchSpec(lr_keys=keys, hr_keys=("hr/fbeta_used",), lr_window=1, hr_window=1, crop=8, depth_ref=False,
                     reflectance_range=(0.5, 2.0))
    cache.ensure(spec.cache_keys)
    sampler = TrainSampler([cache], spec, batch_size=4, seed=2)
    seen = 0
    for b, s, batch in ((b, s, batch) for step in range(12) for batch, samples in [sampler.batch(step)]
                        for b, s in enumerate(samples)):
        assert s.aug.reflectance != (1.0, 1.0, 1.0)
        f = s.frames[-1]
        raw = cache.read(f, "lr/fbeta_used")[s.y0:s.y0 + 8, s.x0:s.x0 + 8]
        unit = apply("x/flags", (raw == 1.0).all(-1, keepdims=True), s.aug)[..., 0]  # geometry only
        got = batch["lr/fbeta_used"][b, -1].transpose(1, 2, 0)
        np.testing.assert_array_equal((got == 1.0).all(-1), unit)
        assert (got[~unit] != 1.0).all()
        seen += int(unit.sum())
        i = batch["lr/irradiance"][b, -1] * batch["lr/fbeta_used"][b, -1] + batch["lr/emission"][b, -1]
        np.testing.assert_allclose(i, batch["lr/radiance"][b, -1], rtol=1e-5, atol=1e-6)
    assert seen > 0  # the crops hold background pixels
