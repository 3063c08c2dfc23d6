"""geometry.alignment: the nearest-point distance of an estimate, and the robust ICP that polishes it,
against float64 brute force."""
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from vrnet_ext.geometry import alignment
from vrnet_ext.geometry.alignment import TurnPrior, multistart_icp, nearest_median, robust_icp
from vrnet_ext.geometry.metrics import rotation_error_deg
from vrnet_ext.geometry.transforms import move


def brute_nearest_median(src, tgt, rotation, translation):
    """float64: the median (the lower one, as torch's) distance from R src + t to the nearest target point."""
    moved = src.double() @ rotation.double().mT + translation.double()[:, None]
    return torch.cdist(moved, tgt.double()).min(dim=-1).values.median(dim=-1).values


def partial_pairs(B=4, N=301, dtype=torch.float32, seed=0, angle=8.0):
    """src (B, N, 3), an anisotropic blob; tgt, the blob moved by a known motion (truth, shift), a
    fifth of it cut away and a little noise added; an estimate ``angle`` degrees (about a random
    axis) and 0.035 off the truth."""
    rng = np.random.default_rng(seed)
    src = torch.from_numpy(rng.normal(size=(B, N, 3)) * [1.0, 0.6, 0.3]).to(dtype)
    truth = torch.from_numpy(Rotation.random(B, random_state=seed).as_matrix()).to(dtype)
    shift = torch.from_numpy(rng.normal(size=(B, 3)) * 0.2).to(dtype)
    tgt = move(src, truth, shift)
    keep = tgt[..., 0] - tgt[..., 0].mean(dim=1, keepdim=True) < tgt[..., 0].quantile(0.8, dim=1, keepdim=True)
    tgt = torch.stack([t[k][: int(keep.sum(dim=1).min())] for t, k in zip(tgt, keep)])
    tgt = tgt + 0.002 * torch.from_numpy(rng.normal(size=tgt.shape)).to(dtype)
    axes = rng.normal(size=(B, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    wrong = torch.from_numpy(Rotation.from_rotvec(axes * np.deg2rad(angle)).as_matrix()).to(dtype)
    return src, tgt, truth, shift, wrong @ truth, shift + 0.02


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("offset", [0.0, 1000.0])
def test_nearest_median_is_the_brute_force_distance(dtype, offset):
    src, tgt, _, _, rotation, translation = partial_pairs(B=3, N=97, dtype=dtype)
    src, tgt = src + offset, tgt + offset  # both far from the origin: R (src - o) + t + o ~ tgt
    translation = translation + offset - (rotation @ torch.full((3, 3, 1), offset, dtype=dtype))[..., 0]
    got = nearest_median(src, tgt, rotation, translation)
    tolerance = (1e-9 if dtype == torch.float64 else 1e-6) * (1 + offset)  # the moved coordinates round
    torch.testing.assert_close(got.double(), brute_nearest_median(src, tgt, rotation, translation),
                               rtol=0, atol=tolerance)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_robust_icp_polishes_an_estimate_a_few_degrees_off(dtype):
    src, tgt, truth, shift, rotation, translation = partial_pairs(dtype=dtype)
    before = rotation_error_deg(rotation, truth)
    polished_R, polished_t = robust_icp(src, tgt, rotation, translation, 30)
    after = rotation_error_deg(polished_R, truth)
    assert polished_R.dtype == dtype and polished_t.shape == (4, 3)
    assert (before > 7).all() and (after < 1).all(), (before, after)
    assert (polished_t - shift).norm(dim=-1).max() < 0.05
    assert (brute_nearest_median(src, tgt, polished_R, polished_t)
            < brute_nearest_median(src, tgt, rotation, translation)).all()
    torch.testing.assert_close(torch.linalg.det(polished_R.double()), torch.ones(4, dtype=torch.float64))


def test_robust_icp_is_per_pair_and_zero_steps_keep_the_estimate():
    src, tgt, _, _, rotation, translation = partial_pairs()
    batched = robust_icp(src, tgt, rotation, translation, 5)
    alone = [robust_icp(src[i:i + 1], tgt[i:i + 1], rotation[i:i + 1], translation[i:i + 1], 5) for i in range(4)]
    torch.testing.assert_close(batched[0], torch.cat([a[0] for a in alone]), rtol=1e-5, atol=1e-5)
    kept = robust_icp(src, tgt, rotation, translation, 0)
    assert kept[0] is rotation and kept[1] is translation
    with pytest.raises(ValueError, match="steps"):
        robust_icp(src, tgt, rotation, translation, -1)


def test_robust_icp_leaves_an_exact_estimate_exact():
    src, _, truth, shift, _, _ = partial_pairs(B=2, dtype=torch.float64)
    tgt = move(src, truth, shift)[:, torch.randperm(src.shape[1])]
    R, t = robust_icp(src, tgt, truth, shift, 3)
    torch.testing.assert_close(R, truth, rtol=0, atol=1e-10)
    torch.testing.assert_close(t, shift, rtol=0, atol=1e-10)


def test_both_backends_agree():
    src, tgt, _, _, rotation, translation = partial_pairs(B=2, N=120)
    ext = robust_icp(src, tgt, rotation, translation, 4, backend="ext")
    reference = robust_icp(src, tgt, rotation, translation, 4, backend="torch")
    torch.testing.assert_close(ext[0], reference[0], rtol=0, atol=1e-4)  # four steps of float32 rounding apart
    # torch.cdist's products round small distances (cancellation): a few 1e-5 at distances of 0.004
    torch.testing.assert_close(nearest_median(src, tgt, *ext, backend="torch"), nearest_median(src, tgt, *ext),
                               rtol=0, atol=5e-5)


def test_multistart_icp_registers_any_motion_and_is_per_pair(monkeypatch):
    """Pairs moved by up to a half turn, a fifth of the target cut away: ICP from the identity stays
    in a wrong minimum, from 128 spread starts it finds each motion; a pair gets the same alone as in
    a batch (and in batches of one pair), and the distance it returns is its result's."""
    from vrnet_ext.geometry.transforms import spread_rotations

    src, tgt, truth, shift, _, _ = partial_pairs(B=3, N=160, seed=4)
    starts = torch.as_tensor(spread_rotations(128), dtype=src.dtype)
    near_identity = robust_icp(src, tgt, torch.eye(3).expand(3, 3, 3), tgt.mean(1) - src.mean(1), 50)[0]
    assert (rotation_error_deg(near_identity, truth) > 20).any()
    rotation, translation, distance = multistart_icp(src, tgt, starts)
    assert (rotation_error_deg(rotation, truth) < 1).all(), rotation_error_deg(rotation, truth)
    assert (translation - shift).norm(dim=-1).max() < 0.05
    torch.testing.assert_close(distance.double(), brute_nearest_median(src, tgt, rotation, translation),
                               rtol=0, atol=1e-6)
    monkeypatch.setattr(alignment, "MULTISTART_BATCH", 1)  # one pair per batch of starts
    alone = multistart_icp(src, tgt, starts)
    for got, want in zip(alone, (rotation, translation, distance)):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    few = multistart_icp(src[:1], tgt[:1], starts[:5])  # fewer starts than it keeps: all of them go on
    assert few[0].shape == (1, 3, 3) and few[2].shape == (1,)
    none = multistart_icp(src[:0], tgt[:0], starts)
    assert none[0].shape == (0, 3, 3) and none[1].shape == (0, 3) and none[2].shape == (0,)
    for bad in (starts[:0], starts[:, :2], starts[0]):
        with pytest.raises(ValueError, match="starts"):
            multistart_icp(src, tgt, bad)


def test_multistart_icp_under_a_bound_keeps_only_estimates_within_it():
    """With ``max_turn``, the pairs whose motion turns within the bound are registered as without
    it; a pair whose motion turns further gets an estimate within the bound or the distance inf,
    never one beyond; 180 is no bound; a bound outside (0, 180] is refused."""
    from vrnet_ext.geometry.metrics import turn_deg
    from vrnet_ext.geometry.transforms import spread_rotations

    src, tgt, truth, shift, _, _ = partial_pairs(B=3, N=160, seed=4)  # motions of 116, 142 and 173 degrees
    starts = torch.as_tensor(spread_rotations(128), dtype=src.dtype)
    free = multistart_icp(src, tgt, starts)
    assert (rotation_error_deg(free[0], truth) < 1).all()
    bound = 150.0
    within = turn_deg(truth) <= bound
    assert within.tolist() == [True, True, False]
    rotation, translation, distance = multistart_icp(src, tgt, starts, prior=TurnPrior(max_turn=bound))
    assert (rotation_error_deg(rotation, truth)[within] < 1).all(), rotation_error_deg(rotation, truth)
    finite = torch.isfinite(distance)
    assert (turn_deg(rotation)[finite] <= bound + 1e-6).all() and finite[within].all()
    assert rotation_error_deg(rotation[~within], truth[~within]).min() > 5  # the truth is beyond it
    torch.testing.assert_close(distance[finite].double(),
                               brute_nearest_median(src, tgt, rotation, translation)[finite], rtol=0, atol=1e-6)
    for got, want in zip(multistart_icp(src, tgt, starts, prior=TurnPrior(max_turn=180.0)), free):
        torch.testing.assert_close(got, want)


def test_a_turn_prior_weighs_a_distance_by_the_turn_and_refuses_bad_values():
    """TurnPrior.score: the distance times (1 + penalty x turn / 180), inf beyond the bound; the default
    prior leaves it as it is; values outside the ranges are refused by name."""
    angles = torch.tensor([0.0, 45.0, 90.0, 135.0, 180.0], dtype=torch.float64)
    axis_angles = np.deg2rad(angles.numpy())[:, None] * [[0.6, 0.0, 0.8]]
    rotation = torch.from_numpy(Rotation.from_rotvec(axis_angles).as_matrix())
    distance = torch.tensor([1.0, 2.0, 0.5, 1.5, 3.0], dtype=torch.float64)
    torch.testing.assert_close(TurnPrior().score(rotation, distance), distance)
    torch.testing.assert_close(TurnPrior(penalty=0.5).score(rotation, distance), distance * (1 + 0.5 * angles / 180))
    bounded = TurnPrior(max_turn=100.0, penalty=0.5)
    assert bounded.beyond(rotation).tolist() == [False, False, False, True, True]
    torch.testing.assert_close(bounded.score(rotation, distance)[:3], (distance * (1 + 0.5 * angles / 180))[:3])
    assert torch.isinf(bounded.score(rotation, distance)[3:]).all()
    assert TurnPrior(max_turn=180.0).beyond(rotation).sum() == 0
    for bad in (0.0, -5.0, 180.5, float("nan"), True):
        with pytest.raises(ValueError, match="max_turn"):
            TurnPrior(max_turn=bad)
    for bad in (-0.1, 10.5, float("nan"), float("inf"), True):
        with pytest.raises(ValueError, match="penalty"):
            TurnPrior(penalty=bad)


def test_multistart_icp_with_a_turn_penalty_takes_the_smaller_of_two_equal_fits():
    """A shape the same after a half turn about its shortest axis fits its target equally well by the
    truth and by the truth after that half turn; with a penalty on the turn multistart_icp returns the
    one that turns less (here the truth), its distance weighed by the penalty; without it some pairs
    get the other."""
    from vrnet_ext.geometry.metrics import turn_deg
    from vrnet_ext.geometry.transforms import spread_rotations

    rng = np.random.default_rng(7)
    half = rng.normal(size=(4, 80, 3)) * [1.0, 0.6, 0.3]
    src = torch.from_numpy(np.concatenate([half, half * [-1.0, -1.0, 1.0]], axis=1)).float()  # Rz(180) src = src
    truth = torch.from_numpy(Rotation.from_rotvec(rng.normal(size=(4, 3)) * 0.35).as_matrix()).float()  # ~20-40 deg
    noise = torch.randn(4, 160, 3, generator=torch.Generator().manual_seed(0))
    tgt = move(src, truth, torch.zeros(4, 3)) + 0.002 * noise
    flip = truth @ torch.diag(torch.tensor([-1.0, -1.0, 1.0]))
    assert (turn_deg(flip) > turn_deg(truth) + 60).all()
    starts = torch.as_tensor(spread_rotations(128), dtype=src.dtype)
    plain_R, _, _ = multistart_icp(src, tgt, starts)
    assert (rotation_error_deg(plain_R, flip) < 1).any(), "without a penalty some pair takes the flip"
    rotation, translation, distance = multistart_icp(src, tgt, starts, prior=TurnPrior(penalty=0.2))
    assert (rotation_error_deg(rotation, truth) < 1).all(), rotation_error_deg(rotation, truth)
    torch.testing.assert_close(distance.double(), brute_nearest_median(src, tgt, rotation, translation)
                               * (1 + 0.2 * turn_deg(rotation) / 180), rtol=0, atol=1e-6)


def cut_views(B=3, seed=0, points=600, noise=0.005):
    """src (B, points, 3) and tgt: views of an elongated, lopsided cloud (a bar with six blobs along it),
    src cut off above x = 0.6 and tgt below x = -0.6 (their centroids lie about 0.3 apart along the
    bar), tgt moved by a known motion (truth, shift); a little noise on both."""
    rng = np.random.default_rng(seed)
    blobs = np.array([[-0.9, 0.3, 0.0], [-0.55, -0.2, 0.25], [-0.2, 0.0, -0.35], [0.15, 0.35, 0.1],
                      [0.5, -0.3, -0.1], [0.85, 0.1, 0.3]])
    views, truths, shifts = ([], []), [], []
    for b in range(B):
        count = 6000
        bar = np.stack([rng.uniform(-1, 1, count), np.zeros(count), np.zeros(count)], 1) + rng.normal(size=(count, 3)) * 0.03
        blob = blobs[rng.integers(0, len(blobs), count)] + rng.normal(size=(count, 3)) * 0.06
        cloud = np.where((rng.uniform(size=count) < 0.5)[:, None], blob, bar)
        truth, shift = Rotation.random(random_state=seed * 10 + b).as_matrix(), rng.normal(size=3) * 0.2
        for view, kept, moved in ((views[0], cloud[:, 0] < 0.6, False), (views[1], cloud[:, 0] > -0.6, True)):
            part = cloud[kept][rng.choice(int(kept.sum()), points, replace=False)] + noise * rng.normal(size=(points, 3))
            view.append(part @ truth.T + shift if moved else part)
        truths.append(truth)
        shifts.append(shift)
    src, tgt, truth, shift = (torch.as_tensor(np.stack(x), dtype=torch.float32) for x in (*views, truths, shifts))
    return src, tgt, truth, shift


def test_multistart_icp_slides_reach_views_whose_centroids_lie_apart():
    """Two views cut from opposite ends of a lopsided bar: from the centroids' translation no start
    registers any pair, with either ICP; with 17 slides along the target's longest axis trimmed ICP
    registers every pair, robust ICP two of three (it drifts off the truth of partial views), each
    nearer the target than without the slides."""
    from vrnet_ext.geometry.transforms import spread_rotations

    src, tgt, truth, shift = cut_views(seed=1)
    starts = torch.as_tensor(spread_rotations(128))
    registered = {}
    for icp in ("robust", "trimmed"):
        centroids = multistart_icp(src, tgt, starts, slide_count=1, icp=icp)
        assert (rotation_error_deg(centroids[0], truth) > 20).all(), rotation_error_deg(centroids[0], truth)
        rotation, translation, distance = multistart_icp(src, tgt, starts, slide_count=17, icp=icp)
        right = (rotation_error_deg(rotation, truth) < 5) & ((translation - shift).norm(dim=-1) < 0.05)
        registered[icp] = int(right.sum())
        torch.testing.assert_close(distance.double(), brute_nearest_median(src, tgt, rotation, translation),
                                   rtol=0, atol=1e-6)
        assert (distance[right] < centroids[2][right]).all()
    assert registered == {"robust": 2, "trimmed": 3}, registered


def test_slides_spread_along_the_longest_axis():
    """One slide: none; an odd count: evenly over +- SEARCH_ICP_SLIDE_REACH standard deviations along
    the target's longest axis, none among them; the same for any translation of the target; bad
    counts refused."""
    from vrnet_ext.names import MAX_SEARCH_ICP_SLIDES, SEARCH_ICP_SLIDE_REACH

    rng = np.random.default_rng(3)
    axis = np.array([2.0, 1.0, -2.0]) / 3
    tgt = torch.from_numpy(rng.normal(size=(500, 1)) * 0.4 * axis + rng.normal(size=(500, 3)) * 0.05)
    assert torch.equal(alignment.slides(tgt, 1), torch.zeros(1, 3, dtype=tgt.dtype))
    offsets = alignment.slides(tgt, 5)
    sd = float((tgt - tgt.mean(0)).double().matmul(torch.from_numpy(axis)).pow(2).mean().sqrt())
    along = offsets.double() @ torch.from_numpy(axis)
    along = along * torch.sign(along[-1])
    torch.testing.assert_close(along, torch.linspace(-1, 1, 5, dtype=torch.float64) * SEARCH_ICP_SLIDE_REACH * sd,
                               rtol=0.02, atol=1e-3)
    assert float(offsets[2].norm()) < 1e-12
    torch.testing.assert_close(alignment.slides(tgt + 7.0, 5).abs(), offsets.abs(), rtol=1e-6, atol=1e-9)
    for bad in (0, MAX_SEARCH_ICP_SLIDES + 1, 2.0, True):
        with pytest.raises(ValueError, match="slides"):
            alignment.slides(tgt, bad)
    src = tgt[None, :50].float()
    with pytest.raises(ValueError, match="icp"):
        multistart_icp(src, src, torch.eye(3)[None], icp="point_to_plane")
    with pytest.raises(ValueError, match="slides"):
        multistart_icp(src[:0], src[:0], torch.eye(3)[None], slide_count=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_trimmed_icp_polishes_and_holds_an_exact_estimate(dtype):
    """Trimmed ICP brings an estimate 8 degrees off a partial, noisy pair within 1 degree (as robust
    ICP does), leaves an exact estimate of an exact pair exact, is per pair, and both backends agree."""
    src, tgt, truth, shift, rotation, translation = partial_pairs(dtype=dtype)
    R, t = alignment.trimmed_icp(src, tgt, rotation, translation, 30)
    assert (rotation_error_deg(R, truth) < 1).all(), rotation_error_deg(R, truth)
    alone = [alignment.trimmed_icp(src[i:i + 1], tgt[i:i + 1], rotation[i:i + 1], translation[i:i + 1], 30)
             for i in range(src.shape[0])]
    torch.testing.assert_close(torch.cat([a[0] for a in alone]), R, rtol=1e-4, atol=1e-4)
    exact = move(src, truth, shift)
    R0, t0 = alignment.trimmed_icp(src, exact, truth, shift, 3)
    torch.testing.assert_close(R0, truth, rtol=0, atol=1e-4 if dtype == torch.float32 else 1e-9)
    reference = alignment.trimmed_icp(src, tgt, rotation, translation, 4, backend="torch")
    ext = alignment.trimmed_icp(src, tgt, rotation, translation, 4, backend="ext")
    torch.testing.assert_close(ext[0], reference[0], rtol=0, atol=1e-4 if dtype == torch.float32 else 1e-9)
    with pytest.raises(ValueError, match="steps"):
        alignment.trimmed_icp(src, tgt, rotation, translation, -1)
