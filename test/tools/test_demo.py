"""``gpis-grasp demo --bag`` on bags other than the simulated ones: the settings it reads from a bag, the
shipped one-frame real captures (bags/real/*.mcap) end to end, and the README's "Record a capture and replay
it" steps, as written, on a synthetic RealSense recording made here.

The demo runs as a subprocess (its own rclpy context and DDS participant; its whole output is checked for
stray error lines)."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gpis_grasp_ros.core.noise_model import SensorModel
from gpis_grasp_ros.data import bagio, messages
from gpis_grasp_ros.tools import demo, import_rgbd
from support.tilted_scene import Box, TiltedScene  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
REAL = sorted((ROOT / 'bags' / 'real').glob('*.mcap'))
#: the target pixels bags/real/README.md lists for the two captures
REAL_TARGETS = {'cleargrasp_000000080_bottle': (220.75, 160.75), 'cleargrasp_000000123_flower_box': (200.75, 122.75)}
STRAY = ('Destroyable', 'Traceback', '[ERROR]', 'Exception')


def run_demo(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get('PYTHONPATH', '')]))
    return subprocess.run([sys.executable, '-m', 'gpis_grasp_ros.tools.demo', *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=900)


def check_planned(proc: subprocess.CompletedProcess, executed: bool) -> str:
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    for line in out.splitlines():
        assert not any(s in line for s in STRAY), f'stray line: {line}'
    for method in demo.METHODS:
        row = next(line for line in proc.stdout.splitlines() if line.startswith(method + ' '))
        assert 'no grasp' not in row
        assert bool(re.search(r'\d+/\d+', row)) == executed, row
    return out


# ------------------------------------------------------------------------------------------ settings
def test_settings_of_the_real_captures_come_from_the_bag():
    assert [p.stem for p in REAL] == sorted(REAL_TARGETS)
    for bag in REAL:
        s = demo.replay_settings(bag)
        assert (s.frames, s.frames_to_average, s.min_frames) == (1, 1, 1)
        assert s.sensor_model == 'realsense_d400' and s.target == 'pixel'
        assert s.target_point == REAL_TARGETS[bag.stem] and s.ground_truth and not s.notes
    override = demo.replay_settings(REAL[0], sensor='carmine', target_pixel=(10.0, 20.0))
    assert (override.sensor_model, override.target_point) == ('carmine', (10.0, 20.0))


def test_settings_of_a_simulated_bag_are_the_node_defaults():
    s = demo.replay_settings(ROOT / 'bags' / 'A_tape_dispenser.mcap')
    assert (s.frames, s.frames_to_average, s.min_frames) == (10, demo.FRAMES_TO_AVERAGE, demo.MIN_FRAMES) == (10, 10, 3)
    assert (s.sensor_model, s.target, s.ground_truth, s.notes) == ('carmine', 'largest', True, [])


def _copy_without_metadata(src: Path, dst: Path) -> None:
    """``src`` rewritten without its custom metadata, as a bag recorded elsewhere would be."""
    info = bagio.bag_topics(src)
    with bagio.BagWriter(dst) as bag:
        for topic, entry in info.items():
            bag.add_topic(topic, entry['type'], entry['qos'])
        for record in bagio.iter_bag(src):
            bag.write_raw(record.topic, record.t_ns, record.raw)


def test_a_bag_without_metadata_says_which_options_to_pass(tmp_path):
    bag = tmp_path / 'recorded.mcap'
    _copy_without_metadata(REAL[0], bag)
    assert bagio.bag_custom_data(bag) == {}
    assert 'gpis_grasp_ros.data.rgbd_import' in bagio.bag_custom_data(REAL[0])
    s = demo.replay_settings(bag)
    assert (s.frames_to_average, s.sensor_model, s.target) == (1, 'carmine', 'largest')
    text = ' '.join(s.notes)
    assert '--sensor realsense_d400' in text and '--target-pixel U V' in text
    assert not demo.replay_settings(bag, sensor='realsense_d400', target_pixel=(220.75, 160.75)).notes
    with pytest.raises(ValueError, match='shipped layout'):
        demo.replay_settings(_points_free(tmp_path))


def _points_free(tmp_path: Path) -> Path:
    """A rosbag2 directory with custom metadata and no cloud topic."""
    path = tmp_path / 'no_cloud'
    f = messages.RosbagsFactory(bagio.get_typestore())
    with bagio.BagWriter(path, custom_data={'gpis_grasp_ros.x': '{"sensor": "realsense_d400"}'}) as bag:
        bag.add_topic('/camera/rgb/camera_info', 'sensor_msgs/msg/CameraInfo', bagio.SENSOR_QOS)
        bag.write('/camera/rgb/camera_info', 1, messages.intrinsics_to_camera_info(
            f, 100.0, 100.0, 10.0, 10.0, 20, 20, messages.header(f, 1, 'cam')))
    assert bagio.bag_custom_data(path) == {'gpis_grasp_ros.x': '{"sensor": "realsense_d400"}'}  # metadata.yaml
    return path


# ------------------------------------------------------------------------------------------ end to end
@pytest.mark.parametrize('bag', REAL, ids=lambda p: p.stem)
def test_demo_on_the_real_captures(bag, tmp_path):
    out = check_planned(run_demo(['--bag', str(bag), '--out', str(tmp_path), '--trials', '5'], tmp_path),
                        executed=True)
    assert '1 frame(s); frames_to_average 1, sensor_model realsense_d400, target pixel' in out
    summary = json.loads((tmp_path / bag.stem / 'summary.json').read_text())
    assert summary['segmentation']['target_point'] == list(REAL_TARGETS[bag.stem])
    assert all(row['success'] and row['sim_trials'] == 5 for row in summary['methods'])


def _readme_recording_steps() -> tuple[str, list[str]]:
    """The python heredoc and the shell lines of the README's "Record a capture and replay it" block."""
    text = (ROOT / 'README.md').read_text()
    section = text[text.index('**Record a capture and replay it.**'):]
    block = section[section.index('```bash\n') + 8:]
    block = block[:block.index('\n```')]
    code = block[block.index("<<'PY'"):]
    code = code[code.index('\n') + 1:code.index('\nPY\n')]
    lines = block.replace('\\\n', ' ').splitlines()
    return code, [line.split('#')[0].strip() for line in lines if not line.startswith((' ', 'import', 'from'))]


def _write_realsense_recording(path: Path, scene: TiltedScene, rgb: np.ndarray, depth: np.ndarray) -> None:
    """What ``ros2 bag record`` of realsense-ros's three topics gives: a rosbag2 directory, 16UC1 depth in mm,
    colour first with a frame of its own (no depth of that stamp), then colour + depth pairs."""
    f = messages.RosbagsFactory(bagio.get_typestore())
    rgb_t, depth_t, info_t = ('/camera/camera/color/image_raw', '/camera/camera/aligned_depth_to_color/image_raw',
                              '/camera/camera/color/camera_info')
    i = scene.intrinsics
    with bagio.BagWriter(path) as bag:
        bag.add_topic(rgb_t, 'sensor_msgs/msg/Image', bagio.SENSOR_QOS)
        bag.add_topic(depth_t, 'sensor_msgs/msg/Image', bagio.SENSOR_QOS)
        bag.add_topic(info_t, 'sensor_msgs/msg/CameraInfo', bagio.SENSOR_QOS)
        t0 = 1_700_000_000_000_000_000
        bag.write(rgb_t, t0, messages.numpy_to_image(f, rgb[-1], 'rgb8', messages.header(f, t0, 'cam')))
        for k in range(len(rgb) - 1):
            t = t0 + (k + 1) * 33_000_000
            h = messages.header(f, t, 'camera_color_optical_frame')
            bag.write(info_t, t, messages.intrinsics_to_camera_info(f, i.fx, i.fy, i.cx, i.cy, i.width, i.height, h))
            bag.write(rgb_t, t, messages.numpy_to_image(f, rgb[k], 'rgb8', h))
            bag.write(depth_t, t + 1, messages.numpy_to_image(f, depth[k], '16UC1', h))


def test_readme_recording_steps_work_as_written(tmp_path):
    code, lines = _readme_recording_steps()
    record = next(line for line in lines if line.startswith('ros2 bag record'))
    assert shlex.split(record)[3:] == ['-o', 'capture', '/camera/camera/color/image_raw',
                                       '/camera/camera/aligned_depth_to_color/image_raw',
                                       '/camera/camera/color/camera_info']
    scene = TiltedScene(45.0, boxes=[Box(0.0, 0.01, 0.03, 0.02, 0.04)], width=320, height=240, focal_px=300.0)
    rgb, depth, label = scene.frames(3, seed=4, model=SensorModel.named('realsense_d400'))
    _write_realsense_recording(tmp_path / 'capture', scene, rgb, depth)

    # the frame extraction, as written
    subprocess.run([sys.executable, '-', 'capture'], input=code, cwd=tmp_path, check=True, text=True, timeout=300,
                   env=dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get('PYTHONPATH', '')])))
    assert np.allclose(np.load(tmp_path / 'depth.npy'), np.round(depth[0] * 1000) / 1000, atol=1e-6, equal_nan=True)

    # import-rgbd, as written
    imp = shlex.split(next(line for line in lines if line.startswith('gpis-grasp import-rgbd')))
    cwd = Path.cwd()
    os.chdir(tmp_path)
    try:
        assert import_rgbd.main(imp[2:]) == 0
    finally:
        os.chdir(cwd)

    # the demo, as written, with the pixel of the box
    v, u = np.nonzero(label == 1)
    assignment = next(line for line in lines if line.startswith('U='))
    assert re.fullmatch(r'U=\d+\.\d V=\d+\.\d', assignment), assignment
    pixel = {'$U': f'{u.mean():.1f}', '$V': f'{v.mean():.1f}'}
    command = next(line for line in lines if line.startswith('gpis-grasp demo'))
    args = [pixel.get(a, a) for a in shlex.split(command)[2:]]
    out = check_planned(run_demo([*args, '--out', str(tmp_path / 'out')], tmp_path), executed=False)
    assert 'frames_to_average 1, sensor_model realsense_d400, target pixel' in out
    assert 'has no ground truth' in out
