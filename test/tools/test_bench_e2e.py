"""``python -m gpis_grasp_ros.bench e2e``: registered, its bags exist, its whole-frame scenes are uncropped
(no timing here: speed targets live in the benchmark)."""

from __future__ import annotations

from gpis_grasp_ros.tools import bench, bench_e2e


def test_e2e_is_a_bench_suite() -> None:
    assert bench.SUITES['e2e'] == 'gpis_grasp_ros.tools.bench_e2e'
    assert bench.main(['no-such-suite']) == 2


def test_bag_cases_exist() -> None:
    for case in bench_e2e.bag_cases():
        assert (bench_e2e.BAG_DIR / case.path).is_file(), case.path


def test_whole_frame_scene_is_not_cropped() -> None:
    rgb, depth, intrinsics = bench_e2e.whole_frame_scene(320, 240, frames=1)
    assert rgb.shape == (1, 240, 320, 3) and depth.shape == (1, 240, 320)
    assert (intrinsics.width, intrinsics.height) == (320, 240)


def test_warm_chain_keeps_the_previous_fit_and_plans_the_same_grasp() -> None:
    """The warm chain of an unchanged scene keeps the warm-up chain's C and l after one likelihood evaluation
    (so the same posterior), starts most restarts at the warm-up plan's optima and, each of them already at
    an optimum, ends at the same grasp; the drifted start is re-searched back."""
    case = bench_e2e.bag_cases()[0]
    scene = bench_e2e.load_bag(bench_e2e.BAG_DIR / case.path, frames=case.frames)
    planner = bench_e2e.PlannerParams()
    cold = bench_e2e.time_chain(scene, case.sensing, planner, 0)
    warm = bench_e2e.time_chain(scene, case.sensing, planner, 0, cold)
    assert not cold['fit'].warm_started and cold['ev'] > 1
    assert warm['fit'].warm_started and not warm['fit'].searched and warm['ev'] == 1
    assert (warm['fit'].signal_variance, warm['fit'].length_scale) == (cold['fit'].signal_variance,
                                                                       cold['fit'].length_scale)
    assert sum(r.warm for r in warm['grasp'].restarts) == 15 and not any(r.warm for r in cold['grasp'].restarts)
    assert abs(warm['grasp'].objective - cold['grasp'].objective) < 1e-9
    assert abs(warm['P_F'] - cold['P_F']) < 1e-9
    times, fit = bench_e2e.time_drifted(cold['grids'], cold['fit'], 1)
    assert len(times) == 1 and fit.warm_started and fit.searched and 1 < fit.n_evaluations <= 10  # cold: 6
    assert abs(fit.log_likelihood - cold['fit'].log_likelihood) < 1e-3


def test_bursts_are_the_two_halves() -> None:
    assert bench_e2e.bursts(10) == (slice(0, 5), slice(5, 10))
    assert bench_e2e.bursts(7) == (slice(0, 3), slice(3, 6))
    assert bench_e2e.bursts(1) == (slice(0, 1), slice(0, 1))


def test_pf_is_a_bench_suite() -> None:
    from gpis_grasp_ros.tools import bench_pf

    assert bench.SUITES['pf'] == 'gpis_grasp_ros.tools.bench_pf'
    for bag in ('A_tape_dispenser', 'head/A_tape_dispenser'):
        assert (bench_pf.BAG_DIR / f'{bag}.mcap').is_file()


def test_whole_frame_target_pixel_is_the_largest_object_in_its_window() -> None:
    """The bench's target-pixel row (the principal point) selects the object the largest-object row does (its table
    colour learnt around it, so a few edge pixels differ), segmented in its window of the frame."""
    from gpis_grasp_ros.core.sensing import SensingParams, segment_frames

    rgb, depth, intr = bench_e2e.whole_frame_scene(480, 360, frames=1)
    largest = segment_frames(rgb, depth, intr, SensingParams())
    at_pixel = segment_frames(rgb, depth, intr, SensingParams(target='pixel', target_point=(intr.cx, intr.cy)))
    assert largest.window_px is None and at_pixel.window_px is not None
    u0, v0, u1, v1 = at_pixel.window_px
    assert (u1 - u0 + 1) * (v1 - v0 + 1) < 0.5 * intr.width * intr.height
    both, either = largest.object_mask & at_pixel.object_mask, largest.object_mask | at_pixel.object_mask
    assert both.sum() >= 0.98 * either.sum()
    assert at_pixel.geometry.shape == largest.geometry.shape
