"""planner_node: serves ``plan_grasp`` (service GraspPlan and action PlanGrasp) on the latest GPIS.

Subscribes ``gpis/model`` (latched), plans with GP-GPIS-OPT or a baseline (paper sections VI,
VII-B), answers with stamped jaw poses in the sensor frame (metres), and publishes
``grasp/markers`` (RViz) and ``grasp/image`` (the grasp drawn on the GPIS-Blur image).

**Many callers.** Requests (service calls and action goals alike) go into one bounded FIFO queue
(``max_queue`` waiting requests) served by ``workers`` planning threads. A request that finds the
queue full is answered at once: ``success=false``, "planner queue full: N requests waiting
(max_queue=N) ...". Every admitted request is answered within ``planning_timeout`` (counted from
the moment planning starts) plus the time it waited in the queue. Planning is cooperatively
cancellable (:class:`gpis_grasp_ros.core.planners.PlanControl`): a timeout, an action cancel or
shutdown stops the computation at the planner's next checkpoint (milliseconds on a 25 x 25 grid)
and the worker takes the next request at once. The service keeps a request history of
:data:`~gpis_grasp_ros.ros.nodes.common.SERVICE_QUEUE_DEPTH` so that a burst of calls is not
dropped by DDS before the node takes it. A waiting service call holds no thread: the service answers
from the planning thread (:class:`~gpis_grasp_ros.ros.nodes.replies.DeferredService`, which sends an
answer again when the middleware could not deliver it). The answer is built in the planning thread too,
so per-thread scratch memory (the contact search's workspace) exists for ``workers`` threads only.

**Asking again.** A service call with a non-zero seed is idempotent: the same request (method, N_g or
K, λ, seed) on the same model and parameters joins the plan in progress or gets the answer already given
(the last :data:`ANSWERS_KEPT`), so a caller that got no answer may send it again without the node
planning twice. (Planning is deterministic given the seed, so another caller sending the same seeded
request gets the grasp it would have got; rclpy does not tell a service who called.)

**Replanning.** With ``warm_start`` (default on) GP-GPIS-OPT, GP-D and GP-U on a newer model of the same
frame start SCP at the local optima of the last plan with that method (:mod:`~gpis_grasp_ros.core.planners.
warm_start`): those still valid on the new mean shape, at most 3/4 of N_g, fresh heuristic grasps for the rest.
A request on the model already planned on starts fresh, so its answer depends on the model and the seed only.

**The first model.** A request arriving before any model waits up to ``model_wait`` s for one (a
model published just before the request may still be being taken) before it is answered
"no GPIS received yet".

**Bad input.** A GpisModel is checked against the node's limits before anything is allocated
(:func:`gpis_grasp_ros.ros.validation.check_gpis_model`) and the rebuilt posterior must be finite;
a rejected model is logged with the offending field and the previous model stays in use.
Requests with an unknown method, N_g/K above its limit, or λ outside the parameter's range are
answered ``success=false`` with the reason.
"""

from __future__ import annotations

import collections
import math
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup

from gpis_grasp_interfaces.action import PlanGrasp
from gpis_grasp_interfaces.msg import GpisModel
from gpis_grasp_interfaces.srv import GraspPlan
from gpis_grasp_ros.core import planners
from gpis_grasp_ros.core.blur import gpis_blur
from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.ros import conversions, validation
from gpis_grasp_ros.ros.nodes import plan_output
from gpis_grasp_ros.ros.nodes.common import (
    LATCHED_QOS,
    SERVICE_QOS,
    SHUTTING_DOWN,
    GuardedNode,
    guarded,
    log_startup,
    run_node,
    trim_heap,
)
from gpis_grasp_ros.ros.nodes.replies import DeferredService, Reply
from gpis_grasp_ros.ros.nodes.shared_params import (
    GRIPPER,
    check_gripper,
    check_resolutions,
    grid_limits,
    gripper_params,
)
from gpis_grasp_ros.ros.params import Param, ParamTable

MAX_INITIAL_GRASPS = 1000
#: Methods whose request field num_initial_grasps means K heuristic grasp samples.
SAMPLING_METHODS = ('gp-m', 'gp-p')
MAX_GRASP_SAMPLES = 100000
#: Upper bound of the max_queue parameter (a waiting action goal holds an executor thread; a service call none).
MAX_QUEUE_LIMIT = 1024
MAX_WORKERS = 8
#: Executor threads for action goals waiting for their plan (see PlannerNode.executor_threads).
ACTION_GOAL_THREADS = 16
#: Seconds between heap trims while new models arrive (common.trim_heap).
TRIM_PERIOD = 2.0
#: Answers to seeded service calls kept for callers that ask again (cleared when a new model arrives).
ANSWERS_KEPT = 256
#: (frame_id, method) pairs whose last plan's optima are kept as warm starts (least recently planned dropped).
WARM_STARTS_KEPT = 16
#: Range of the uncertainty_penalty parameter; requests outside it (other than negative = default) are rejected.
LAMBDA_RANGE = (0.0, 1.0e8)


@dataclass(frozen=True)
class PlannerConfig:
    """The planner_node parameters in effect (built and validated by :func:`build_config`).

    ``planner`` holds the request defaults (N_g, K, λ); a request's own values replace them.
    """

    planner: planners.PlannerParams = field(default_factory=planners.PlannerParams)
    method: str = 'gp-gpis-opt'  # used when a request leaves method empty
    planning_timeout: float = 60.0  # s of planning after which a request is stopped
    model_wait: float = 5.0  # s a request arriving before any model waits for one
    image_scale: int = 16  # pixels per grid cell of grasp/image
    max_queue: int = 32  # requests that may wait for a worker
    workers: int = 1  # planning threads
    limits: validation.Limits = field(default_factory=validation.Limits)
    grasp_height: float = -1.0  # m above the table; negative = automatic (conversions.grasp_height_for)
    object_height: float = 0.0  # m, for the automatic grasp height; 0 = unknown
    jaw_height: float = conversions.DEFAULT_JAW_HEIGHT  # m, jaw pad height along the approach
    warm_start: bool = True  # SCP planners start at the previous model's optima (core/planners/warm_start.py)

    @property
    def gripper(self) -> GripperParams:
        return self.planner.gripper


_PP = planners.PlannerParams
PARAMETERS = ParamTable('planner_node', [
    Param('method', str, 'planner used when a request leaves method empty', PlannerConfig,
          choices=tuple(planners.METHODS)),
    Param('num_initial_grasps', int, 'N_g: random initial grasps of GP-GPIS-OPT / GP-D / GP-U (paper: 20)', _PP,
          'n_initial_grasps', low=1, high=MAX_INITIAL_GRASPS),
    Param('num_grasp_samples', int, 'K: heuristic grasp samples of GP-M and GP-P (paper: 1000)', _PP,
          'n_grasp_samples', low=1, high=MAX_GRASP_SAMPLES),
    Param('num_shape_samples', int, 'S: GPIS shape samples of the Monte-Carlo P_F estimate (paper: 1000)', _PP,
          'n_shape_samples', low=10, high=100000),
    Param('num_perturbations', int, 'K_p: jaw perturbations averaged in the smoothed P_F of GP-GPIS-OPT / GP-D / GP-U '
          '(16 plans in about half the time, P_F 0.01 lower: docs/speed.md)', _PP, 'n_perturbations', low=1,
          high=1000),
    Param('uncertainty_penalty', float, 'lambda of eq. 4, per m^2 of SDF variance at the contacts (the same on any '
          'grid; the paper\'s 2 per cell^2 is 5e4 at 6.3 mm cells); requests outside this range are rejected', _PP,
          unit='1/m^2', low=LAMBDA_RANGE[0],
          high=LAMBDA_RANGE[1]),
    Param('antipodal_alpha', float, 'alpha of eq. 5: bound on |n1 + n2|^2 of the antipodal constraint', _PP,
          low=0.0, high=4.0),
    Param('warm_start', bool, 'replanning: GP-GPIS-OPT / GP-D / GP-U on a newer model of the same frame start at the '
          'previous plan\'s local optima still valid on the new mean shape (at most 3/4 of N_g; fresh heuristic grasps '
          'for the rest); false = fresh starts only, each plan reproducible from its model and seed',
          PlannerConfig),
    Param('gp_p_adaptive', bool, 'GP-P: successive-halving Monte Carlo (true) or every candidate on all S shape '
          'samples as in the paper (false); the final choice uses all S either way', _PP),
    *gripper_params(('jaw_width', 'max_opening', 'friction_coefficient', 'position_noise', 'contact_patch')),
    GRIPPER['jaw_height'].replace(target=PlannerConfig),
    Param('planning_timeout', float, 'planning time after which a request is stopped and answered success=false '
          '(queueing time not included)', PlannerConfig, unit='s', low=0.1, high=3600.0),
    Param('model_wait', float, "a request arriving before the first GPIS model waits this long for one before "
          "it is answered 'no GPIS received yet'", PlannerConfig, unit='s', low=0.0, high=60.0),
    Param('image_scale', int, 'pixels per grid cell of grasp/image', PlannerConfig, low=1, high=64),
    Param('grasp_height', float, 'height above the table, along its normal, of the jaw poses and contacts; '
          'negative = automatic: half of object_height, at least half of jaw_height', PlannerConfig, unit='m',
          low=-1.0, high=0.5),
    Param('object_height', float, 'height of the object above the table for the automatic grasp_height; 0 = the '
          'height measured by segmentation (GpisModel.object_height; if that is 0 too, unknown: the jaws close '
          'half a jaw height above the table); > 0 overrides it', PlannerConfig, unit='m', low=0.0,
          high=validation.MAX_OBJECT_HEIGHT),
    Param('max_queue', int, "requests (service calls + action goals) that may wait for a worker; more are "
          "answered 'queue full' at once", PlannerConfig, low=0, high=MAX_QUEUE_LIMIT),
    Param('workers', int, 'planning threads working on requests in parallel', PlannerConfig, low=1,
          high=MAX_WORKERS, read_only=True),
    *grid_limits('GpisModel', 250000),
], checks=[check_gripper, check_resolutions])


def build_config(v: dict[str, Any]) -> PlannerConfig:
    """Parameter values → :class:`PlannerConfig`; ValueError names the offending parameter."""
    gripper = GripperParams(**PARAMETERS.kwargs(v, GripperParams))
    config = PARAMETERS.kwargs(v, PlannerConfig)
    if config['method'] not in planners.METHODS:
        raise ValueError(f"method={config['method']!r} is not one of {', '.join(planners.METHODS)}")
    # a model narrower than a jaw pad cannot be planned on (validation.check_map_meta_data)
    limits = validation.Limits(**PARAMETERS.kwargs(v, validation.Limits), min_extent=gripper.jaw_width)
    return PlannerConfig(planner=planners.PlannerParams(gripper=gripper, **PARAMETERS.kwargs(v, _PP)),
                         limits=limits, **config)


@dataclass(eq=False)
class PlanJob:
    """One admitted request (service call or action goal) and its outcome."""

    method: str
    n: int
    lam: float
    seed: int
    posterior: Any
    model: Any
    blur: np.ndarray
    config: PlannerConfig
    cancelled: Any = None                 # callable -> reason or None (action cancel)
    on_progress: Any = None               # callable(PlanProgress)
    enqueued: float = field(default_factory=time.monotonic)
    started: float | None = None
    deadline: float = math.inf
    result: Any = None
    error: BaseException | None = None
    stopped: str = ''
    done: threading.Event = field(default_factory=threading.Event)
    response: Any = None                  # GraspPlan.Response or PlanGrasp.Result, filled when answered
    replies: list = field(default_factory=list)  # service callers waiting for this job (DeferredService)
    key: tuple | None = None              # idempotency key of a seeded service call
    answered: bool = False


class PlannerNode(GuardedNode):
    """Thin ROS wrapper around :func:`gpis_grasp_ros.core.planners.plan` with a bounded request queue."""

    #: Bounded: every thread the executor ever started keeps its own scratch memory (malloc arena, numpy
    #: temporaries), so RSS grows with the thread count. Service calls hold none while they wait; an action
    #: goal holds one until answered, so up to ACTION_GOAL_THREADS goals wait at once (more are accepted and
    #: taken as threads free up). The model callback, parameters and services share the rest.
    executor_threads = ACTION_GOAL_THREADS + 4

    def __init__(self, **kwargs) -> None:
        super().__init__('planner_node', **kwargs)
        self.config: PlannerConfig = PARAMETERS.watch(self, build_config, self._apply_config)
        self.workers = self.config.workers

        self._lock = threading.Lock()
        self._model_ready = threading.Condition(self._lock)  # notified when a model is taken
        self._model: GpisModel | None = None
        self._posterior = None
        self._blur: np.ndarray | None = None

        self._queue: collections.deque[PlanJob] = collections.deque()
        self._running: set[PlanJob] = set()
        self._queue_cv = threading.Condition()
        self._workers = [threading.Thread(target=self._work, name=f'grasp-planning-{i}', daemon=True)
                         for i in range(self.workers)]
        for worker in self._workers:
            worker.start()

        self._model_topic = 'gpis/model'
        self.create_subscription(GpisModel, self._model_topic, guarded(self, self._model_topic, self._on_model),
                                 LATCHED_QOS, callback_group=MutuallyExclusiveCallbackGroup())
        self.visuals = plan_output.GraspVisuals(self)
        self._answers: collections.OrderedDict[tuple, Any] = collections.OrderedDict()  # key -> response
        self._keyed: dict[tuple, PlanJob] = {}  # key -> job in progress
        self._answer_basis: tuple = (None, None)  # the model and configuration the kept answers were planned with
        #: (frame_id, method) -> (the model planned on, its plan's optima): the next model's SCP starts
        self._warm: collections.OrderedDict[tuple[str, str], tuple[Any, planners.WarmStart]] = \
            collections.OrderedDict()
        self._watchdog = threading.Thread(target=self._watch_deadlines, name='grasp-planning-deadlines', daemon=True)
        self._watchdog.start()
        requests = ReentrantCallbackGroup()
        self.plan_service = DeferredService(self, GraspPlan, 'plan_grasp', self._on_plan, SERVICE_QOS,
                                            callback_group=requests)
        self._action = ActionServer(self, PlanGrasp, 'plan_grasp', execute_callback=self._execute_goal,
                                    goal_callback=self._on_goal, cancel_callback=lambda _goal: CancelResponse.ACCEPT,
                                    callback_group=requests, goal_service_qos_profile=SERVICE_QOS,
                                    result_service_qos_profile=SERVICE_QOS, cancel_service_qos_profile=SERVICE_QOS)
        log_startup(self, [self._model_topic], ['grasp/markers', 'grasp/image'],
                    ['method', 'num_initial_grasps', 'num_shape_samples', 'uncertainty_penalty', 'planning_timeout',
                     'max_queue', 'workers'], services=['plan_grasp'], actions=['plan_grasp'])

    def _apply_config(self, config: PlannerConfig) -> None:
        self.config = config

    # ------------------------------------------------------------------ model input
    def _on_model(self, msg: GpisModel) -> None:
        try:
            validation.check_gpis_model(msg, self.config.limits)
            posterior = messages.gpis_model_to_posterior(msg)
            validation.check_posterior(posterior)
        except (ValueError, np.linalg.LinAlgError) as exc:
            self.reject(f'ignoring GpisModel on {self.resolve_topic_name(self._model_topic)}: {exc}; '
                                      'keeping the previous model')
            return
        blur = gpis_blur(posterior, n_samples=200, rng=np.random.default_rng(0))
        with self._model_ready:
            self._model, self._posterior, self._blur = msg, posterior, blur
            self._model_ready.notify_all()
        g = posterior.geometry
        self.get_logger().info(f'GPIS received: {g.height}x{g.width} cells of {g.resolution * 1000:.1f} mm '
                               f"in '{g.frame_id}'")

    def has_model(self) -> bool:
        """Whether a GPIS model has been received and is ready for planning."""
        with self._lock:
            return self._posterior is not None

    def _latest_model(self, wait: float) -> tuple[Any, Any, Any]:
        """(model, posterior, blur) of the latest GPIS; before the first, wait up to ``wait`` s for one
        (or until shutdown): a model published just before the request may still be being taken."""
        deadline = time.monotonic() + wait
        with self._model_ready:
            while self._posterior is None and not self.shutting_down.is_set():
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._model_ready.wait(min(left, 0.05))
            return self._model, self._posterior, self._blur

    # ------------------------------------------------------------------ requests
    def _make_job(self, method_field: str, n_field: int, lam_field: float, seed_field: int) -> PlanJob | str:
        """Validate a request (service or goal) → a job, or the reason it is rejected."""
        config = self.config
        method = method_field or config.method  # exactly one of the names; empty = the node's method
        if method not in planners.METHODS:
            return (f"unknown method '{method_field}'; valid: {', '.join(planners.METHODS)} (exactly; empty = the "
                    f"node's method '{config.method}')")
        sampling = method in SAMPLING_METHODS
        default_n = config.planner.n_grasp_samples if sampling else config.planner.n_initial_grasps
        limit = MAX_GRASP_SAMPLES if sampling else MAX_INITIAL_GRASPS
        n = int(n_field) or int(default_n)
        if n > limit:
            return f'num_initial_grasps={n_field} is too large for {method} (at most {limit})'
        lam = float(lam_field)
        if not math.isfinite(lam):
            return f'uncertainty_penalty must be a finite number, got {lam}'
        if lam < 0:
            lam = config.planner.uncertainty_penalty
        elif lam > LAMBDA_RANGE[1]:
            return (f'uncertainty_penalty={lam} is outside the parameter range [{LAMBDA_RANGE[0]:g}, '
                    f'{LAMBDA_RANGE[1]:g}] (negative = use the node parameter)')
        model, posterior, blur = self._latest_model(config.model_wait)
        if posterior is None:
            return ('no GPIS received yet: waiting for a gpis_grasp_interfaces/msg/GpisModel on '
                    f"'{self.resolve_topic_name(self._model_topic)}' (waited model_wait={config.model_wait:g} s)")
        seed = int(seed_field) if seed_field else int(np.random.SeedSequence().entropy % (2 ** 32))
        return PlanJob(method=method, n=n, lam=lam, seed=seed, posterior=posterior, model=model, blur=blur,
                       config=config)

    def _submit(self, job: PlanJob) -> str | None:
        """Queue ``job``; the reason when it cannot be queued (queue full, shutting down)."""
        with self._queue_cv:
            if self.shutting_down.is_set():
                return f'planner_node is {SHUTTING_DOWN}'
            if len(self._queue) >= job.config.max_queue:
                return (f'planner queue full: {len(self._queue)} requests waiting (max_queue={job.config.max_queue}) '
                        f'and {len(self._running)} planning; retry later')
            self._queue.append(job)
            self._queue_cv.notify_all()  # the workers and the deadline watchdog wait on it
        return None

    def queue_length(self) -> int:
        """Requests waiting for a worker."""
        with self._queue_cv:
            return len(self._queue)

    def _wait(self, job: PlanJob) -> None:
        """Block until the job is answered (finished, stopped, past its deadline, or shutting down)."""
        job.done.wait()

    def _watch_deadlines(self) -> None:
        """Answer a running job at its deadline (or at shutdown) even if the planner has not reached its
        next checkpoint yet; the worker stops there and then takes the next request."""
        trimmed_for, next_trim = None, 0.0
        while True:
            with self._queue_cv:
                self._queue_cv.wait(0.02)
                running = list(self._running)
                stopping = self.shutting_down.is_set()
            with self._lock:
                model = self._model
            if model is not trimmed_for and time.monotonic() > next_trim:  # models replaced: free their pages
                trim_heap()
                trimmed_for, next_trim = model, time.monotonic() + TRIM_PERIOD
            now = time.monotonic()
            for job in running:
                if stopping:
                    self._finish(job, SHUTTING_DOWN)
                elif job.started is not None and now > job.deadline:
                    self._finish(job, 'timeout')
            if stopping and not running:
                with self._queue_cv:
                    if not self._running and not self._queue:
                        return

    def _finish(self, job: PlanJob, stopped: str = '') -> None:
        """Answer the job once (its service callers and its action goal): the first call wins."""
        with self._queue_cv:
            if job.answered:
                return
            job.answered = True
            if stopped:
                job.stopped = job.stopped or stopped
        if job.response is None:
            job.response = GraspPlan.Response()
        try:
            plan_output.fill_answer(job.response, job, self.get_logger(), self.visuals)
        except Exception as exc:  # noqa: BLE001 - the callers always get an answer
            job.response.success = False
            job.response.message = f'internal error in plan_grasp: {type(exc).__name__}: {exc}'
            self.get_logger().error(job.response.message)
        with self._queue_cv:
            replies, job.replies = job.replies, []
            if job.key is not None and self._keyed.get(job.key) is job:
                del self._keyed[job.key]
                if job.model is self._answer_basis[0] and job.config is self._answer_basis[1]:
                    self._answers[job.key] = job.response
                    while len(self._answers) > ANSWERS_KEPT:
                        self._answers.popitem(last=False)
        job.done.set()
        for reply in replies:
            reply.send(job.response)
            self.exit_callback()

    def _work(self) -> None:
        while True:
            with self._queue_cv:
                while not self._queue and not self.shutting_down.is_set():
                    self._queue_cv.wait()
                if self.shutting_down.is_set():
                    queued = list(self._queue)
                    self._queue.clear()
                    break
                job = self._queue.popleft()
                self._running.add(job)
            try:
                self._run(job)
                self._finish(job)
            finally:
                with self._queue_cv:
                    self._running.discard(job)
        for job in queued:
            self._finish(job, SHUTTING_DOWN)

    def _run(self, job: PlanJob) -> None:
        job.started = time.monotonic()
        job.deadline = job.started + job.config.planning_timeout

        def should_stop() -> str | None:
            if self.shutting_down.is_set():
                return SHUTTING_DOWN
            if job.cancelled is not None and job.cancelled():
                return 'cancelled'
            if time.monotonic() > job.deadline:
                return 'timeout'
            return None

        control = planners.PlanControl(should_stop=should_stop, on_progress=job.on_progress)
        params = self._planner_params(job)
        try:
            job.result = planners.plan(job.method, job.posterior, params, seed=job.seed, control=control,
                                       warm_start=self._warm_start(job))
            job.stopped = job.stopped or str(getattr(job.result, 'stopped', '') or '')
            self._keep_optima(job)
        except Exception as exc:  # noqa: BLE001 - reported to the caller, never kills the node
            job.error = exc

    def _warm_start(self, job: PlanJob) -> planners.WarmStart | None:
        """The optima of the last plan with this method on an older model of the job's frame (warm_start on)."""
        if not job.config.warm_start or job.method not in planners.WARM_METHODS:
            return None
        with self._lock:
            kept = self._warm.get((job.posterior.geometry.frame_id, job.method))
        return None if kept is None or kept[0] is job.model else kept[1]

    def _keep_optima(self, job: PlanJob) -> None:
        """Keep a finished plan's optima as the next model's warm start (the last plan to finish wins)."""
        result = job.result
        if job.method not in planners.WARM_METHODS or result is None or result.stopped or not result.restarts:
            return
        optima = planners.WarmStart.from_result(result, job.posterior.geometry)
        key = (job.posterior.geometry.frame_id, job.method)
        with self._lock:
            self._warm[key] = (job.model, optima)
            self._warm.move_to_end(key)
            while len(self._warm) > WARM_STARTS_KEPT:
                self._warm.popitem(last=False)

    def _planner_params(self, job: PlanJob) -> planners.PlannerParams:
        """The node's planner settings with the request's N_g or K and λ."""
        p = job.config.planner
        sampling = job.method in SAMPLING_METHODS
        return replace(p, n_initial_grasps=p.n_initial_grasps if sampling else job.n,
                       n_grasp_samples=job.n if sampling else p.n_grasp_samples, uncertainty_penalty=job.lam)

    def _on_plan(self, request: GraspPlan.Request, reply: Reply) -> None:
        """A service call: answered at once (refused, asked again) or later by the planning thread."""
        response = reply.response
        response.success = False
        if self.shutting_down.is_set():
            response.message = f'{self.get_name()} is {SHUTTING_DOWN}'
            reply.send()
            return
        key = None
        if request.seed:
            key = (str(request.method), int(request.num_initial_grasps),
                   float(request.uncertainty_penalty), int(request.seed))
        with self._queue_cv:
            self._forget_answers_of_old_models()
            answer = self._answers.get(key) if key is not None else None
            if answer is not None:  # asked again: the answer already given
                self._answers.move_to_end(key)
            elif key is not None and key in self._keyed and self._keyed[key].config is self.config:
                # asked again while planning: join that job
                self.enter_callback()
                self._keyed[key].replies.append(reply)
                return
        if answer is not None:
            reply.send(answer)
            return
        job = self._make_job(request.method, request.num_initial_grasps, request.uncertainty_penalty, request.seed)
        if isinstance(job, str):
            response.message = job
            reply.send()
            return
        job.response, job.replies = response, [reply]
        self.enter_callback()
        with self._queue_cv:
            if key is not None and job.model is self._answer_basis[0] and job.config is self._answer_basis[1]:
                job.key = key
                self._keyed[key] = job
        refused = self._submit(job)
        if refused is not None:
            with self._queue_cv:
                if job.key is not None and self._keyed.get(job.key) is job:
                    del self._keyed[job.key]
                job.replies = []
            response.message = refused
            reply.send()
            self.exit_callback()

    def _forget_answers_of_old_models(self) -> None:
        """Kept answers belong to one model and one configuration (caller holds the queue lock)."""
        with self._lock:
            basis = (self._model, self.config)
        if basis[0] is not self._answer_basis[0] or basis[1] is not self._answer_basis[1]:
            self._answers.clear()
            self._answer_basis = basis

    # ------------------------------------------------------------------ action
    def _on_goal(self, _goal: Any) -> GoalResponse:
        # Every goal is accepted and answered with a result; invalid or refused goals are aborted
        # with the reason in result.message (a rejected goal could not say why).
        return GoalResponse.ACCEPT

    def _execute_goal(self, goal_handle: Any) -> PlanGrasp.Result:
        self.enter_callback()
        try:
            return self._execute_goal_inner(goal_handle)
        finally:
            self.exit_callback()

    def _execute_goal_inner(self, goal_handle: Any) -> PlanGrasp.Result:
        result = PlanGrasp.Result()
        result.success = False
        goal = goal_handle.request
        job = self._make_job(goal.method, goal.num_initial_grasps, goal.uncertainty_penalty, goal.seed)
        if isinstance(job, str):
            result.message = job
            goal_handle.abort()
            return result
        start = time.monotonic()

        def progress(p: planners.PlanProgress) -> None:
            fb = PlanGrasp.Feedback(restarts_done=int(p.restarts_done), restarts_total=int(p.restarts_total),
                                    best_objective=float(p.best_objective),
                                    best_probability_force_closure=float(p.best_p_f),
                                    elapsed=time.monotonic() - start)
            try:
                goal_handle.publish_feedback(fb)
            except Exception:  # noqa: BLE001 - feedback is best effort (e.g. during shutdown)
                pass

        job.cancelled = lambda: goal_handle.is_cancel_requested
        job.on_progress = progress
        job.response = result
        refused = self._submit(job)
        if refused is not None:
            result.message = refused
            goal_handle.abort()
            return result
        self._wait(job)
        if job.stopped == 'cancelled':
            goal_handle.canceled()
        elif result.success:
            goal_handle.succeed()
        else:
            goal_handle.abort()
        return result

    # ------------------------------------------------------------------ shutdown
    def begin_shutdown(self) -> None:
        queue_cv = getattr(self, '_queue_cv', None)  # None while __init__ has not made it yet
        if queue_cv is None:
            super().begin_shutdown()
            return
        with queue_cv:
            super().begin_shutdown()
            queue_cv.notify_all()

    def destroy_node(self) -> None:
        self.begin_shutdown()
        self.plan_service.close()
        try:
            self._action.destroy()
        except Exception:  # noqa: BLE001 - already destroyed
            pass
        super().destroy_node()



def main(args: list[str] | None = None) -> int:
    return run_node(PlannerNode, args)


if __name__ == '__main__':
    sys.exit(main())
