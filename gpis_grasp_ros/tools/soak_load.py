"""The load phases of ``gpis-grasp soak``: the concurrency matrix, the model stream and parameter latency.

* **matrix**: planner_node restarted for each ``workers`` value, ``max_queue`` set at run time, then
  bursts and closed loops from 1-10 *new client processes* at once, each calling right after its
  ``wait_for_service`` returned (the moment a new client's first answers can be lost while
  discovery lags under CPU load). Every request must be answered: planned, or refused with a reason.
* **models**: GPIS models published in a loop into planner_node, a plan every so often; its RSS
  sampled, the slope after warm-up in MB per 1000 models.
* **parameter latency**: a pinger process asks each node for a parameter every 50 ms during the whole run
  (while estimates, fits and plans run); p50/p99/max per node.

Client processes run this module: ``python -m gpis_grasp_ros.tools.soak_load client ...`` prints one
JSON line with its counts and latencies.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

#: Requests of the matrix: cheap plans (GP-M, K samples, the planner's S set small at start-up).
MATRIX_METHOD = 'gp-m'
MATRIX_K = 5
MATRIX_SHAPE_SAMPLES = 10
#: (client processes, requests per client, mode) of every cell of the matrix.
MATRIX_ROUNDS = ((1, 100, 'burst'), (5, 40, 'burst'), (10, 100, 'burst'), (10, 10, 'loop'))
MATRIX_WORKERS = (1, 2, 4)
MATRIX_QUEUES = (32, 128, 1024)
#: How long the pinger waits for a parameter answer before it counts the call as unanswered (s).
PING_WAIT_S = 5.0


def rss_mb(pid: int, field: str = 'VmRSS') -> float:
    """A memory figure of ``pid`` from /proc (MB): ``VmRSS`` resident now, ``VmHWM`` its peak; NaN when gone."""
    try:
        text = Path(f'/proc/{pid}/status').read_text()
    except OSError:
        return float('nan')
    m = re.search(rf'{field}:\s+(\d+) kB', text)
    return int(m.group(1)) / 1024 if m else float('nan')


def threads(pid: int) -> int:
    """Threads of ``pid``."""
    try:
        return int(re.search(r'Threads:\s+(\d+)', Path(f'/proc/{pid}/status').read_text()).group(1))
    except (OSError, AttributeError):
        return -1


def slope_per_1000(xs: list[float], ys: list[float]) -> float:
    """Least-squares slope of ``ys`` over ``xs``, per 1000 units of x."""
    if len(xs) < 3:
        return float('nan')
    return float(np.polyfit(np.asarray(xs, float), np.asarray(ys, float), 1)[0] * 1000)


def slope_with_error_per_1000(xs: list[float], ys: list[float], blocks: int = 8) -> tuple[float, float]:
    """Slope of ``ys`` over ``xs`` per 1000 units of x, and its standard error from the means of ``blocks``
    consecutive blocks (RSS samples are a sawtooth, not independent: the block means are closer to it)."""
    n = len(xs) // blocks
    if n < 1:
        return float('nan'), float('nan')
    bx = np.asarray(xs[:n * blocks], float).reshape(blocks, n).mean(axis=1)
    by = np.asarray(ys[:n * blocks], float).reshape(blocks, n).mean(axis=1)
    (slope, icpt), cov = np.polyfit(bx, by, 1, cov=True)
    return float(slope * 1000), float(np.sqrt(cov[0, 0]) * 1000)


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float('nan')


# --------------------------------------------------------------------------- client process
def run_client(count: int, mode: str, seed0: int, retry: bool, timeout: float) -> dict[str, Any]:
    """One client process: ``count`` plan_grasp calls at once (burst) or one after the other (loop)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from gpis_grasp_interfaces.srv import GraspPlan
    from gpis_grasp_ros.ros.client import _ask
    from gpis_grasp_ros.ros.nodes.common import SERVICE_QOS

    rclpy.init()
    node = rclpy.create_node(f'soak_client_{os.getpid()}')
    cli = node.create_client(GraspPlan, 'plan_grasp', qos_profile=SERVICE_QOS)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    out: dict[str, Any] = {'sent': count, 'answered': 0, 'planned': 0, 'refused': 0, 'no_reason': 0,
                           'lost': 0, 'latencies': [], 'reasons': {}}
    if not cli.wait_for_service(timeout_sec=60.0):
        out['lost'] = count
        out['error'] = 'service not available'
        return out
    lock = threading.Lock()

    def one(k: int) -> None:
        request = GraspPlan.Request(method=MATRIX_METHOD, num_initial_grasps=MATRIX_K, seed=seed0 + k)
        start = time.monotonic()
        if retry:
            answer = _ask(lambda: cli.call_async(request), cli.remove_pending_request, timeout)
        else:
            done = threading.Event()
            future = cli.call_async(request)
            future.add_done_callback(lambda _f: done.set())
            answer = future.result() if done.wait(timeout) else None
        with lock:
            if answer is None:
                out['lost'] += 1
                return
            out['answered'] += 1
            out['latencies'].append(time.monotonic() - start)
            if answer.success:
                out['planned'] += 1
            elif answer.message.strip():
                out['refused'] += 1
                reason = answer.message.split(':')[0][:40]
                out['reasons'][reason] = out['reasons'].get(reason, 0) + 1
            else:
                out['no_reason'] += 1

    if mode == 'burst':
        threads = [threading.Thread(target=one, args=(k,)) for k in range(count)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    else:
        for k in range(count):
            one(k)
    return out


def run_pinger(nodes: dict[str, str], duration: float, period: float = 0.05) -> dict[str, Any]:
    """A pinger process: asks each node for one parameter every ``period`` s for ``duration`` s (or until
    SIGINT); latencies measured in a process doing nothing else, so the soak's own work (publishing models,
    starting clients) does not delay the answers it counts."""
    import rclpy
    from rcl_interfaces.srv import GetParameters
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from gpis_grasp_ros.ros.nodes.common import SERVICE_QOS

    # SIGINT ends the pinger with its figures: KeyboardInterrupt, even when the soak was started with SIGINT
    # ignored (a background job of a shell), which its children would inherit
    signal.signal(signal.SIGINT, signal.default_int_handler)
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(f'soak_pinger_{os.getpid()}')
    clients = {name: (node.create_client(GetParameters, f'/{name}/get_parameters', qos_profile=SERVICE_QOS), param)
               for name, param in nodes.items()}  # the deep history every plain client needs (docs/reliability.md)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True).start()
    latencies: dict[str, list[float]] = {name: [] for name in nodes}
    unanswered: dict[str, list[float]] = {name: [] for name in nodes}
    end = time.monotonic() + duration
    try:
        _ping(clients, latencies, unanswered, end, period)
    except KeyboardInterrupt:  # the soak is done: SIGINT ends the pinger
        pass
    return latency_table(latencies, unanswered)


def _ping(clients: dict, latencies: dict, unanswered: dict, end: float, period: float) -> None:
    from rcl_interfaces.srv import GetParameters
    while time.monotonic() < end:
        for name, (cli, param) in clients.items():
            if not cli.service_is_ready():
                continue
            done = threading.Event()
            start, sent_at = time.monotonic(), time.time()
            future = cli.call_async(GetParameters.Request(names=[param]))
            future.add_done_callback(lambda _f, d=done: d.set())
            if done.wait(PING_WAIT_S):
                latencies[name].append(time.monotonic() - start)
            else:
                unanswered[name].append(sent_at)
                cli.remove_pending_request(future)
            time.sleep(period)


def latency_table(latencies: dict[str, list[float]], unanswered: dict[str, list[float]]) -> dict[str, Any]:
    """Per node: calls, unanswered (and the wall-clock times they were sent), p50/p99/max (ms)."""
    return {name: {'calls': len(v), 'unanswered': len(unanswered[name]), 'unanswered_sent_at': unanswered[name],
                   'p50_ms': 1000 * _pct(v, 50), 'p99_ms': 1000 * _pct(v, 99),
                   'max_ms': 1000 * max(v) if v else float('nan')}
            for name, v in latencies.items()}


def split_by_restarts(table: dict[str, Any], restarts: list[tuple[str, float, float]],
                      wait_s: float = PING_WAIT_S) -> dict[str, Any]:
    """Splits each node's unanswered calls into those sent to a node the soak was restarting (sent at most
    ``wait_s`` before it was stopped and before its replacement had started: a stopped process answers
    nothing) and the rest, which are the ones that count."""
    for name, row in table.items():
        if not isinstance(row, dict) or 'unanswered_sent_at' not in row:
            continue
        windows = [(stop - wait_s, up) for node, stop, up in restarts if node == name]
        sent = row.pop('unanswered_sent_at')
        during = sum(any(a <= t <= b for a, b in windows) for t in sent)
        row['unanswered_during_restart'] = during
        row['unanswered'] = len(sent) - during
    return table


# --------------------------------------------------------------------------- the soak side
class ParameterPinger:
    """The pinger process (:func:`run_pinger`) over the whole soak: every node asked every ``period`` s."""

    def __init__(self, soak: Any, nodes: dict[str, str], period: float = 0.05, limit_s: float = 7200.0) -> None:
        asked = [x for name, param in nodes.items() for x in ('--node', f'{name}={param}')]
        self.cmd = [sys.executable, '-m', 'gpis_grasp_ros.tools.soak_load', 'pinger', '--duration', str(limit_s),
                    '--period', str(period), *asked]
        self.env = soak.env
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen(self.cmd, env=self.env, stdout=subprocess.PIPE, text=True)

    def stop(self, restarts: list[tuple[str, float, float]] = ()) -> dict[str, Any]:
        """Ends the pinger (SIGINT) and returns its table; ``restarts`` (node, stopped, started again; wall
        clock) separate the calls a restarted node could not answer."""
        self.proc.send_signal(signal.SIGINT)
        out = ''
        try:
            out, _ = self.proc.communicate(timeout=30)
            return split_by_restarts(json.loads(out.strip().splitlines()[-1]), list(restarts))
        except (subprocess.TimeoutExpired, ValueError, IndexError) as e:
            self.proc.kill()
            return {'error': f'the pinger process gave no figures ({type(e).__name__}: {e}; '
                             f'exit code {self.proc.poll()}; its output ended {out[-300:]!r})'}


def _restart_node(soak: Any, name: str, extra: list[str], suffix: str) -> None:
    """Node ``name`` stopped (if running) and started again with ``extra``; the restart's wall-clock window goes
    to ``soak.restarts`` (the parameter pinger's calls into it have no server to answer them)."""
    from gpis_grasp_ros.tools.soak import start_node
    proc = soak.procs.get(name)
    stopped = time.time()
    if proc is not None and proc.poll() is None:
        proc.terminate()
        proc.wait(timeout=20)
    start_node(soak, name, extra, suffix=suffix)
    soak.restarts.append((name, stopped, time.time()))


def _restart_planner(soak: Any, workers: int) -> None:
    """planner_node again with ``workers`` planning threads (read-only) and the matrix's cheap S."""
    from gpis_grasp_ros.tools.soak import NODES
    args = NODES['planner_node']
    extra = [x for flag, value in zip(args[::2], args[1::2], strict=True)
             if not value.startswith(('max_queue', 'workers')) for x in (flag, value)]
    extra += ['-p', f'workers:={workers}', '-p', f'num_shape_samples:={MATRIX_SHAPE_SAMPLES}',
              '-p', f'max_queue:={MATRIX_QUEUES[0]}']
    _restart_node(soak, 'planner_node', extra, f'_w{workers}')


def _wait_planner_model(soak: Any, timeout: float = 60.0) -> bool:
    from gpis_grasp_interfaces.srv import GraspPlan
    cli = soak.plan_client()
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        res, _ = soak.call(cli, GraspPlan.Request(method=MATRIX_METHOD, num_initial_grasps=MATRIX_K, seed=1), 30)
        if res is not None and res.success:
            return True
        time.sleep(0.5)
    return False


def matrix(soak: Any, model: Any, retry: bool, rounds=MATRIX_ROUNDS, workers_values=MATRIX_WORKERS,
           queues=MATRIX_QUEUES, timeout: float = 120.0) -> None:
    """The concurrency matrix (figures in ``soak.figures['matrix']``)."""
    from gpis_grasp_interfaces.msg import GpisModel
    from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS
    pub = soak.node.create_publisher(GpisModel, 'gpis/model', LATCHED_QOS)
    pub.publish(model)
    cells, totals = [], dict.fromkeys(('sent', 'answered', 'planned', 'refused', 'no_reason', 'lost'), 0)
    latencies: list[float] = []
    reasons: dict[str, int] = {}
    started = time.monotonic()
    seed = 1000
    for workers in workers_values:
        _restart_planner(soak, workers)
        if not _wait_planner_model(soak):
            raise RuntimeError('planner_node has no model for the matrix')
        for queue in queues:
            if not soak.set_param('planner_node', 'max_queue', queue):
                raise RuntimeError(f'max_queue={queue} not accepted')
            for n_clients, per_client, mode in rounds:
                procs = []
                for _ in range(n_clients):
                    seed += per_client
                    cmd = [sys.executable, '-m', 'gpis_grasp_ros.tools.soak_load', 'client', '--count',
                           str(per_client), '--mode', mode, '--seed', str(seed), '--timeout', str(timeout)]
                    if retry:
                        cmd.append('--retry')
                    procs.append(subprocess.Popen(cmd, env=getattr(soak, 'client_env', soak.env),
                                                  stdout=subprocess.PIPE, text=True))
                cell = dict.fromkeys(totals, 0)
                for p in procs:
                    try:
                        text, _ = p.communicate(timeout=timeout + 120)
                        res = json.loads(text.strip().splitlines()[-1])
                    except (subprocess.TimeoutExpired, ValueError, IndexError):
                        p.kill()
                        res = {'sent': per_client, 'lost': per_client}
                    for k in cell:
                        cell[k] += int(res.get(k, 0))
                    latencies += res.get('latencies', [])
                    for reason, n in res.get('reasons', {}).items():
                        reasons[reason] = reasons.get(reason, 0) + int(n)
                cells.append({'workers': workers, 'max_queue': queue, 'clients': n_clients, 'mode': mode, **cell})
                for k in totals:
                    totals[k] += cell[k]
    soak.node.destroy_publisher(pub)
    from gpis_grasp_ros.tools.soak import NODES
    _restart_node(soak, 'planner_node', NODES['planner_node'], '_after_matrix')  # the soak's settings again
    soak.figures['matrix'] = {
        'cells': len(cells), 'client_api': 'ask again (client.py)' if retry else 'plain rclpy call_async',
        **{f'requests_{k}': v for k, v in totals.items()},
        'answered_pct': 100.0 * totals['answered'] / max(totals['sent'], 1),
        'latency_p50_s': _pct(latencies, 50), 'latency_p99_s': _pct(latencies, 99),
        'refusal_reasons': reasons,
        'cells_with_losses': [c for c in cells if c['lost']],
        'answers_sent_again': soak.log_count(r'sending it again'),
        'answers_undeliverable': soak.log_count(r'could not be delivered'),
        'wall_clock_s': time.monotonic() - started,
    }
    soak.figures['matrix_cells'] = {f"w{c['workers']} q{c['max_queue']} {c['clients']}x{c['mode']}":
                                    f"{c['answered']}/{c['sent']} answered, {c['planned']} planned, "
                                    f"{c['refused']} refused" for c in cells}


def _quarter_median(ys: list[float], q: int) -> float:
    n = len(ys) // 4
    return float(np.median(ys[q * n:(q + 1) * n])) if n else float('nan')


def model_stream(soak: Any, model: Any, count: int, plan_every: int = 50, rate_hz: float = 100.0,
                 sample_every: int = 100) -> None:
    """``count`` models (each a new message with its own stamp and slightly different targets) published
    into planner_node at ``rate_hz`` (it takes the newest when busy), a plan every ``plan_every``; RSS and
    the models taken so far sampled every ``sample_every`` published. The slope after warm-up (the second
    half) is per 1000 models taken, with its standard error over block means."""
    import copy

    from gpis_grasp_interfaces.msg import GpisModel
    from gpis_grasp_interfaces.srv import GraspPlan
    from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS
    pid = soak.procs['planner_node'].pid
    pub = soak.node.create_publisher(GpisModel, 'gpis/model', LATCHED_QOS)
    cli = soak.plan_client()
    rng = np.random.default_rng(0)
    base_y = np.asarray(model.train_y, dtype=np.float64)
    received_before = soak.log_count(r'GPIS received', ['planner_node'])
    ys, taken, plans_ok, plans = [], [], 0, 0
    failures: dict[str, int] = {}
    started = time.monotonic()
    for k in range(count):
        m = copy.copy(model)
        m.header = copy.deepcopy(model.header)
        m.header.stamp.sec = int(model.header.stamp.sec) + k + 1
        m.train_y = (base_y + rng.normal(0.0, 1e-5, base_y.shape)).tolist()
        pub.publish(m)
        time.sleep(1.0 / rate_hz)
        if k % plan_every == plan_every - 1:
            res, _ = soak.call(cli, GraspPlan.Request(method=MATRIX_METHOD, num_initial_grasps=MATRIX_K,
                                                      seed=k + 1), 60)
            plans += 1
            plans_ok += int(res is not None and res.success)
            if res is None or not res.success:
                reason = 'not answered within 60 s' if res is None else (res.message or 'no reason')[:60]
                failures[reason] = failures.get(reason, 0) + 1
        if k % sample_every == sample_every - 1:
            taken.append(soak.log_count(r'GPIS received', ['planner_node']) - received_before)
            ys.append(rss_mb(pid))
    time.sleep(2.0)
    received = soak.log_count(r'GPIS received', ['planner_node']) - received_before
    half = len(ys) // 2
    slope, slope_se = slope_with_error_per_1000(taken[half:], ys[half:])
    soak.node.destroy_publisher(pub)
    soak.figures['models'] = {
        'published': count, 'taken_by_planner': received, 'plans': plans, 'plans_ok': plans_ok,
        'plan_failures': failures,
        'rss_first_mb': ys[0] if ys else float('nan'), 'rss_last_mb': ys[-1] if ys else float('nan'),
        'rss_max_mb': max(ys) if ys else float('nan'), 'threads_at_end': threads(pid),
        'rss_slope_after_warmup_mb_per_1000_taken': slope, 'rss_slope_after_warmup_standard_error': slope_se,
        'rss_median_second_quarter_mb': _quarter_median(ys, 1), 'rss_median_last_quarter_mb': _quarter_median(ys, 3),
        'wall_clock_s': time.monotonic() - started,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description='a client process of the soak matrix')
    sub = p.add_subparsers(dest='what', required=True)
    c = sub.add_parser('client')
    c.add_argument('--count', type=int, required=True)
    c.add_argument('--mode', choices=('burst', 'loop'), required=True)
    c.add_argument('--seed', type=int, required=True)
    c.add_argument('--timeout', type=float, default=120.0)
    c.add_argument('--retry', action='store_true', help='ask again like GraspPlannerClient')
    g = sub.add_parser('pinger')
    g.add_argument('--node', action='append', required=True, help='NODE=PARAMETER to ask for (repeatable)')
    g.add_argument('--duration', type=float, required=True, help='seconds')
    g.add_argument('--period', type=float, default=0.05, help='seconds between calls')
    a = p.parse_args(argv)
    if a.what == 'pinger':
        nodes = dict(item.split('=', 1) for item in a.node)
        print(json.dumps(run_pinger(nodes, a.duration, a.period)), flush=True)
    else:
        print(json.dumps(run_client(a.count, a.mode, a.seed, a.retry, a.timeout)), flush=True)
    os._exit(0)  # a client process ends here: no teardown of the spinning executor (it would abort)


if __name__ == '__main__':
    sys.exit(main())
