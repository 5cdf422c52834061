"""The plane-select head, its zone planes and the encoder descriptors."""

from __future__ import annotations

import pytest
import torch

from deltar.models import create_model
from deltar.models.affinity import EncoderDescriptors
from deltar.models.decoder import DecoderZones
from deltar.models.heads.footprints import zone_prior_map
from deltar.models.heads.plane_select import PlanarSelectHead, zone_planes


def _grid_rects(grid: int, zone_px: int) -> torch.Tensor:
    rows, cols = torch.meshgrid(torch.arange(grid), torch.arange(grid), indexing="ij")
    y0, x0 = (rows * zone_px).reshape(-1), (cols * zone_px).reshape(-1)
    return torch.stack([y0, x0, y0 + zone_px, x0 + zone_px], dim=-1).float()[None]


def _plane_depth(y: torch.Tensor, x: torch.Tensor, slope_y: float = 0.004,
                 slope_x: float = 0.001) -> torch.Tensor:
    """A slanted floor-like plane: inverse depth affine in the pixel coordinates (1/m)."""
    return 1.0 / (0.2 + slope_y * y + slope_x * x)


def _centres(rects: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    return 0.5 * (rects[..., 0] + rects[..., 2]), 0.5 * (rects[..., 1] + rects[..., 3])


def test_zone_planes_recover_a_plane_and_ignore_a_neighbour_across_a_depth_edge():
    rects = _grid_rects(8, 16)
    cy, cx = _centres(rects)
    means = _plane_depth(cy, cx)
    valid = torch.ones(1, 64, dtype=torch.bool)
    slope_y, slope_x = zone_planes(means.double(), valid, rects.double(), ridge=1e-9,
                                   similarity=10.0)
    # 1/d = (1/m_k)(1 + a dy + b dx) with offsets in zone sizes (16 px).
    inverse = 1.0 / means.double()
    torch.testing.assert_close(slope_y, 0.004 * 16 / inverse, rtol=1e-4, atol=1e-9)
    torch.testing.assert_close(slope_x, 0.001 * 16 / inverse, rtol=1e-4, atol=1e-9)

    # A fronto-parallel wall at 2 m with one zone on an object at 1 m: the wall zones
    # next to it stay flat (the similarity weight drops the object), and the ridge
    # keeps an isolated zone flat.
    wall = torch.full((1, 64), 2.0)
    wall[0, 27] = 1.0
    slope_y, slope_x = zone_planes(wall, valid, rects)
    assert slope_y.abs().max() < 1e-4 and slope_x.abs().max() < 1e-4
    only = torch.zeros(1, 64, dtype=torch.bool)
    only[0, 0] = True
    slope_y, slope_x = zone_planes(wall, only, rects)
    assert slope_y.abs().max() == 0 and slope_x.abs().max() == 0


def test_untrained_flat_head_is_the_zone_prior():
    torch.manual_seed(0)
    head = PlanarSelectHead(temperature=0.0, planar=False, n_bins=8)
    rects = _grid_rects(4, 8).repeat(2, 1, 1)
    means = torch.rand(2, 16) * 3 + 0.5
    valid = torch.rand(2, 16) > 0.2
    descriptors = torch.nn.functional.normalize(torch.randn(2, 6, 16, 16), dim=1)
    depth, edges, spread = head(descriptors, means, valid, rects, stride=2.0)
    torch.testing.assert_close(depth, zone_prior_map(means, valid, rects, (16, 16), 2.0),
                               rtol=1e-5, atol=1e-6)
    assert edges.shape == (2, 9) and (spread >= 0).all()


def test_planar_head_follows_a_slanted_plane_the_flat_head_cannot():
    # A plane from 2.0 to 4.5 m over the 8x8 zones: neighbouring zones differ by about
    # 5-10%, within the planes' similarity scale (steeper changes count as edges).
    rects = _grid_rects(8, 16)
    cy, cx = _centres(rects)
    means = _plane_depth(cy, cx, 0.002, 0.0005)
    valid = torch.ones(1, 64, dtype=torch.bool)
    descriptors = torch.nn.functional.normalize(torch.ones(1, 4, 32, 32), dim=1)
    rows = (torch.arange(32) + 0.5) * 4.0
    truth = _plane_depth(rows[:, None], rows[None, :], 0.002, 0.0005)[None, None]
    errors = {}
    for planar in (True, False):
        head = PlanarSelectHead(temperature=0.0, planar=planar)
        depth, _, _ = head(descriptors, means, valid, rects, stride=4.0)
        errors[planar] = ((depth - truth).abs() / truth).mean().item()
    assert errors[True] < 0.003 and errors[False] > 2 * errors[True]


def test_plane_select_scales_exactly_with_the_zone_readings():
    torch.manual_seed(1)
    head = PlanarSelectHead(temperature=5.0)
    rects = _grid_rects(8, 8)
    means = torch.rand(1, 64) * 2 + 0.5
    valid = torch.rand(1, 64) > 0.15
    descriptors = torch.nn.functional.normalize(torch.randn(1, 6, 16, 16), dim=1)
    depth, _, uncertainty = head(descriptors, means, valid, rects, stride=4.0)
    scaled, _, scaled_uncertainty = head(descriptors, 2.5 * means, valid, rects, stride=4.0)
    torch.testing.assert_close(scaled, 2.5 * depth, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(scaled_uncertainty, 2.5 * uncertainty, rtol=1e-4, atol=1e-6)
    # Never beyond max_ratio of the frame's readings.
    low, high = means[valid].min(), means[valid].max()
    assert depth.min() >= low / 2 - 1e-5 and depth.max() <= 2 * high + 1e-5


def test_affinity_picks_the_zone_that_looks_like_the_pixel():
    # Two 16 px zones read 1 m and 3 m; the left zone looks like channel 1 except its
    # first four columns, which look like the right zone (channel 0).
    rects = torch.tensor([[[0.0, 0.0, 16.0, 16.0], [0.0, 16.0, 16.0, 32.0]]])
    means, valid = torch.tensor([[1.0, 3.0]]), torch.ones(1, 2, dtype=torch.bool)
    descriptors = torch.zeros(1, 2, 16, 32)
    descriptors[:, 0, :, :4] = 1.0
    descriptors[:, 1, :, 4:16] = 1.0
    descriptors[:, 0, :, 16:] = 1.0
    depth = {}
    for temperature in (0.0, 20.0):
        head = PlanarSelectHead(temperature=temperature, planar=False)
        depth[temperature], _, _ = head(descriptors, means, valid, rects, stride=1.0)
    # Without affinity the left columns follow their own zone; with it, their look.
    assert depth[0.0][..., :3].mean() < 1.5
    assert depth[20.0][..., :3].mean() > 2.5 and depth[20.0][..., 6:12].mean() < 1.5


def test_zones_with_no_target_offer_the_far_depth_where_the_pixels_look_like_them():
    # A wall at 2 m on the left half; the right half reported no target. Pixels that look
    # like the right half go to the no-target depth, an absolute that does not scale
    # with the readings; without flags the right half extends the wall.
    rects = _grid_rects(4, 8)
    cols = _centres(rects)[1]
    valid = cols < 16
    far = ~valid
    means = torch.where(valid, torch.tensor(2.0), torch.tensor(0.0))
    descriptors = torch.zeros(1, 2, 32, 32)
    descriptors[:, 0, :, :16] = 1.0
    descriptors[:, 1, :, 16:] = 1.0
    head = PlanarSelectHead(temperature=20.0, no_target_depth=5.0)
    plain, _, _ = head(descriptors, means, valid, rects, stride=1.0)
    flagged, _, _ = head(descriptors, means, valid, rects, stride=1.0, zone_no_target=far)
    assert torch.allclose(plain, torch.tensor(2.0), rtol=1e-4)
    torch.testing.assert_close(flagged[..., :12], torch.full((1, 1, 32, 12), 2.0),
                               rtol=1e-3, atol=1e-3)
    torch.testing.assert_close(flagged[..., 20:], torch.full((1, 1, 32, 12), 5.0),
                               rtol=1e-3, atol=1e-3)
    # Flags on valid zones change nothing; all-False flags are no flags.
    same, _, _ = head(descriptors, means, valid, rects, stride=1.0, zone_no_target=valid)
    torch.testing.assert_close(same, plain)
    none, _, _ = head(descriptors, means, valid, rects, stride=1.0,
                      zone_no_target=torch.zeros_like(valid))
    torch.testing.assert_close(none, plain)
    # Readings divided by a frame scale: the far depth stays at 5 m once scaled back.
    scale = torch.tensor([2.0])
    normalised, _, _ = head(descriptors, means / 2.0, valid, rects, stride=1.0,
                            zone_no_target=far, zone_scale_m=scale)
    torch.testing.assert_close(normalised * 2.0, flagged, rtol=1e-5, atol=1e-5)
    # A close-up frame (readings divided by a 0.3 m scale): still 5 m, not clamped at
    # the head's limit in the scaled units.
    close, _, _ = head(descriptors, means / 6.0, valid, rects, stride=1.0, zone_no_target=far,
                       zone_scale_m=torch.tensor([0.3]))
    torch.testing.assert_close(close[..., 20:] * 0.3, torch.full((1, 1, 32, 12), 5.0),
                               rtol=1e-3, atol=1e-3)
    with pytest.raises(ValueError, match="no_target_depth"):
        PlanarSelectHead(no_target_depth=20.0)
    # None: the flags are ignored (weights saved before them load that way).
    ignoring = PlanarSelectHead(temperature=20.0, no_target_depth=None)
    assert not ignoring.uses_no_target
    same, _, _ = ignoring(descriptors, means, valid, rects, stride=1.0, zone_no_target=far)
    torch.testing.assert_close(same, plain)


def test_network_passes_the_no_target_flags_to_its_head():
    from deltar.models import create_model

    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=(64, 64)).eval()
    image = torch.randn(1, 3, 64, 64)
    rects = _grid_rects(8, 8)
    valid = torch.ones(1, 64, dtype=torch.bool)
    valid[0, 32:] = False
    hypotheses = torch.where(valid[..., None], torch.linspace(1.4, 1.6, 16), 0.0)
    with torch.no_grad():
        plain = model(image, hypotheses, rects, valid)["depth"]
        flagged = model(image, hypotheses, rects, valid, zone_no_target=~valid)["depth"]
    # The lower half reported no target: its depth moves toward 5 m, the top stays.
    assert flagged[..., 24:, :].mean() > plain[..., 24:, :].mean() + 1.0
    torch.testing.assert_close(flagged[..., :4, :], plain[..., :4, :], rtol=0.05, atol=0.05)
    with pytest.raises(ValueError, match="zone_no_target"):
        model(image, hypotheses, rects, valid, zone_no_target=valid[:, :10])
    with pytest.raises(ValueError, match="zone_no_target"):
        model(image, hypotheses, rects, valid, zone_no_target=valid.float())


def test_checkpoints_saved_before_the_flags_ignore_them(tmp_path):
    from deltar.models import create_model
    from deltar.models.checkpoint import load_checkpoint, save_checkpoint

    model = create_model("deltar-select", design_size=(64, 64))
    path = save_checkpoint(tmp_path / "new.pt", model, "deltar-select")
    assert load_checkpoint(path)[0].uses_no_target
    payload = torch.load(path, weights_only=False)
    # As files written before the flags: format 2, flat options, no no_target_depth.
    flat = model.network_config.flat_options()
    del flat["no_target_depth"]
    torch.save({**payload, "format_version": 2, "config": flat}, tmp_path / "old.pt")
    old, _, config = load_checkpoint(tmp_path / "old.pt")
    assert not old.uses_no_target and config["output"]["no_target_depth"] is None


def test_encoder_descriptors_are_unit_vectors_at_the_output_stride():
    module = EncoderDescriptors((16, 24, 40, 112, 320), strides=(8, 16), out_stride=4)
    assert module.channels == 152
    features = [torch.randn(2, c, 64 // s, 96 // s)
                for c, s in zip((16, 24, 40, 112, 320), (2, 4, 8, 16, 32), strict=True)]
    out = module(features, DecoderZones((64, 96)))
    assert out.shape == (2, 152, 16, 24)
    torch.testing.assert_close(out.norm(dim=1), torch.ones(2, 16, 24))
    with pytest.raises(ValueError, match="descriptor strides"):
        EncoderDescriptors((16, 24, 40, 112, 320), strides=(6,))


def test_descriptor_network_needs_a_selecting_head():
    from deltar.models import create_model

    with pytest.raises(ValueError, match="decoder 'descriptors'"):
        create_model("deltar-lite", decoder="descriptors", head="bins")
    model = create_model("deltar-lite", decoder="descriptors", head="plane_select",
                         design_size=(64, 96)).eval()
    rects = _grid_rects(8, 8) * torch.tensor([1.0, 1.5, 1.0, 1.5])
    hypotheses = torch.rand(1, 64, 16) * 2 + 1
    out = model(torch.rand(1, 3, 64, 96), hypotheses, rects, torch.ones(1, 64, dtype=torch.bool))
    assert out["depth"].shape == (1, 1, 32, 48) and out["uncertainty"].shape == (1, 1, 32, 48)
    assert torch.isfinite(out["depth"]).all()
    learned = [n for n, p in model.named_parameters() if not n.startswith("image_encoder.")]
    assert sorted(learned) == ["decoder.channel_weight", "head.temperature"]


def test_plane_select_checkpoint_round_trip_keeps_the_design(tmp_path):
    from deltar.models import create_model
    from deltar.models.checkpoint import load_checkpoint, save_checkpoint

    torch.manual_seed(0)
    model = create_model("deltar-lite", decoder="descriptors", head="plane_select",
                         planar=False, select_temperature=3.0, design_size=(64, 96))
    with torch.no_grad():
        model.decoder.channel_weight.uniform_(0.5, 1.5)
    save_checkpoint(tmp_path / "m.pt", model, "deltar-lite")
    loaded, preset, _ = load_checkpoint(tmp_path / "m.pt")
    assert preset == "deltar-lite" and loaded.network_config.decoder.name == "descriptors"
    assert loaded.network_config.head.planar is False and not loaded.head.planar
    torch.testing.assert_close(loaded.decoder.channel_weight, model.decoder.channel_weight)
    assert loaded.head.temperature.item() == pytest.approx(3.0)


def test_select_preset_trains_only_its_descriptor_weights_and_temperature():
    from deltar.models import create_model, list_presets

    assert "deltar-select" in list_presets()
    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=(64, 96))
    assert model.network_config.decoder.name == "descriptors"
    assert model.distribution_encoder is None
    rects = _grid_rects(8, 8) * torch.tensor([1.0, 1.5, 1.0, 1.5])
    out = model(torch.rand(2, 3, 64, 96), torch.rand(2, 64, 16) * 2 + 1, rects.repeat(2, 1, 1),
                torch.rand(2, 64) > 0.2)
    (out["depth"].log().mean() + out["uncertainty"].mean()).backward()
    for name in ("decoder.channel_weight", "head.temperature"):
        grad = dict(model.named_parameters())[name].grad
        assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0, name


def test_a_black_frame_trains_without_nan_gradients():
    # An all-zero image gives all-zero descriptors somewhere: their normalisation must
    # have finite gradients, or one such frame would poison the learned numbers.
    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=(64, 96)).train()
    image = torch.zeros(1, 3, 64, 96)
    hypotheses = torch.full((1, 64, 16), 2.0)
    ys, xs = torch.meshgrid(torch.arange(8.0), torch.arange(8.0), indexing="ij")
    rects = torch.stack([ys * 8, xs * 12, ys * 8 + 8, xs * 12 + 12], -1).reshape(1, 64, 4)
    out = model(image, hypotheses, rects, torch.ones(1, 64, dtype=torch.bool))
    out["depth"].log().mean().backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)


@pytest.mark.parametrize(("size_in", "size_out"), [(16, 64), (20, 80), (32, 64), (5, 7),
                                                   (7, 5), (1, 4), (3, 3)])
def test_bilinear_matrix_is_torch_linear_resizing(size_in, size_out):
    import torch.nn.functional as F

    from deltar.models.affinity import bilinear_matrix

    x = torch.randn(2, 3, size_in)
    expected = F.interpolate(x, size=size_out, mode="linear", align_corners=False)
    got = x @ torch.from_numpy(bilinear_matrix(size_in, size_out)).T
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-6)


def _weighted_descriptors(image_size: tuple[int, int], seed: int):
    """Descriptors over four encoder levels with random channel weights, and random
    encoder maps (batch 2) for an image of ``image_size`` pixels."""
    torch.manual_seed(seed)
    descriptors = EncoderDescriptors([16, 24, 40, 112], strides=(8, 16), out_stride=4)
    with torch.no_grad():
        descriptors.channel_weight.uniform_(0.5, 1.5)
    height, width = image_size
    features = [torch.randn(2, c, -(-height // s), -(-width // s))
                for c, s in zip([16, 24, 40, 112], (2, 4, 8, 16), strict=True)]
    return descriptors, features


@pytest.mark.parametrize("image_size", [(64, 96), (56, 88), (96, 64)])
def test_the_exported_descriptors_are_the_descriptors(image_size):
    """The export's form (centred and weighted before a whole-factor upsampling, resized
    by matrix products, both norms from one convolution) gives forward's values; 56x88
    has stride-16 maps of 3.5x5.5 cells, resized by a fractional factor."""
    descriptors, features = _weighted_descriptors(image_size, seed=3)
    height, width = image_size
    zones = DecoderZones(image_size=image_size)
    with torch.no_grad():
        expected = descriptors(features, zones)
        got = descriptors._export_forward(features, (height // 4, width // 4))
    torch.testing.assert_close(got, expected, rtol=0, atol=2e-6)


@pytest.mark.parametrize("image_size", [(64, 96), (56, 88), (96, 64)])
def test_the_factored_descriptors_give_the_descriptors_products(image_size):
    """The export's factored form (coarse maps, bilinear matrices, per-cell factors whose
    norms come from neighbouring coarse cells) gives the descriptors themselves, their
    footprint sums and their dot products with a table, as forward's descriptors do;
    56x88 resizes by a fractional factor."""
    from deltar.models.affinity import FactoredDescriptors

    descriptors, features = _weighted_descriptors(image_size, seed=4)
    height, width = image_size
    with torch.no_grad():
        expected = descriptors(features, DecoderZones(image_size=image_size))
        factored = descriptors._factored(features, (height // 4, width // 4))
        assert isinstance(factored, FactoredDescriptors)
        assert tuple(factored.shape) == tuple(expected.shape)
        torch.testing.assert_close(factored.materialise(), expected, rtol=0, atol=2e-6)
        h, w = expected.shape[-2:]
        weights_y, weights_x = torch.rand(2, h, 5), torch.rand(2, w, 5)
        pooled = torch.einsum("bchw,bhz,bwz->bcz", expected, weights_y, weights_x)
        torch.testing.assert_close(factored.pool(weights_y, weights_x), pooled,
                                   rtol=1e-5, atol=1e-5)
        table = torch.randn(2, expected.shape[1], 7)
        dots = torch.einsum("bchw,bcn->bhwn", expected, table)
        torch.testing.assert_close(factored.dot(table), dots, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize(("coarse", "fine"), [((16, 20), (64, 80)), ((4, 6), (7, 11)),
                                              ((6, 5), (3, 4)), ((1, 3), (4, 9))])
def test_upsampled_square_norms_from_the_coarse_map(coarse, fine):
    from deltar.models.affinity import _upsampled_square_norms, bilinear_matrix

    torch.manual_seed(5)
    part = torch.randn(2, 6, *coarse)
    kernel = torch.rand(2, 6)
    rows, cols = bilinear_matrix(coarse[0], fine[0]), bilinear_matrix(coarse[1], fine[1])
    upsampled = torch.from_numpy(rows) @ part @ torch.from_numpy(cols).T
    expected = torch.einsum("kc,bchw->bkhw", kernel, upsampled * upsampled)
    torch.testing.assert_close(_upsampled_square_norms(part, kernel, rows, cols), expected,
                               rtol=1e-5, atol=1e-5)
