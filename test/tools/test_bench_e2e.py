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
