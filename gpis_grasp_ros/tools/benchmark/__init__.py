"""``gpis-grasp benchmark``: the paper's Table I, Fig. 4, Fig. 5, runtime scaling and a calibration study.

    gpis-grasp benchmark [--bags bags/*.mcap] [--out out/benchmark] [--workers N] [--seeds 3]
                         [--grasp-samples 1000] [--shape-samples 1000] [--trials 20] [--methods gp-m,gp-g,...]
                         [--calibration [--calibration-candidates 200] [--calibration-trials 50]] [--fig5]
    gpis-grasp benchmark --scaling [--object A] [--sizes 25,40,55,70,100] [--repeats 3]

**Table I run.** For every bag the GPIS is built exactly as the ROS nodes build it
(:func:`~gpis_grasp_ros.data.bags.load_bag` + :func:`~gpis_grasp_ros.data.bags.posterior_from_scene`,
M = 25), then every method of :data:`METHODS` plans with the paper's settings (N_g = 20, λ = 2,
K = 1000 heuristic grasp samples, S = 1000 shape samples, σ_g = 0.5 cell) for ``--seeds`` seeds.
GP-P is run brute force (``gp_p_adaptive=False``, as in the paper) and, as an extra row, with
the default successive halving. Recorded per object × method × seed (``results.csv``):

* ``p_f`` ± ``p_f_std_error`` — the planners' own Monte-Carlo P_F of the chosen grasp on S shape
  samples and perturbations of the seed's *evaluation* stream (independent of the samples used
  for selection);
* ``q_f_mean`` — Ferrari–Canny Q_F of the grasp on the GPIS mean shape (planning grid);
* ``q_n`` — Ferrari–Canny Q_N of the *unperturbed* grasp on the TRUE shape of the bag
  (``/ground_truth/sdf``, 1 mm grid): contacts by :func:`~gpis_grasp_ros.core.contacts.find_contacts`
  on the true SDF, centre of mass = the bag's true centre of mass, ρ = radius of gyration of the
  true shape. A grasp without contact, with a jaw starting inside the true object or wider than
  w_g has no Q_N (NaN, reason in ``q_n_status``; counted as 0 in the tables' means);
* ``sim_successes`` of ``sim_trials`` executions by the simulated gripper on the true shape
  (:func:`~gpis_grasp_ros.sim.execution.execute_grasp_trials`, σ_g = 0.5 planning cell, true COM);
* ``planning_time_s`` (time to choose the grasp, what the paper's runtime columns report) and
  ``evaluation_time_s`` (the final P_F estimate);
* ``converged`` (the chosen restart met the SCP convergence test), ``restarts`` and
  ``restarts_converged`` for the optimisers.

**Timing protocol**: every method is timed the same way —
each plan once per seed by the planner's own clock (from the call to the choice of the grasp,
without the final P_F evaluation), one object per process with one BLAS thread, the methods of
an object run one after the other. Tables report the worst case over seeds (the paper's
statistic) and the median over seeds; per-object GP-P / GP-G ratios are summarised by their mean
and their median over objects. The scaling study times everything as the minimum of
``--repeats`` runs.

**Methods.** The paper's five (GP-M, GP-D and GP-U with N_g = 20 starts, GP-P brute force,
GP-G) plus clearly labelled extras: GP-P adaptive, GP-G re-ranked, GP-D / GP-U from one start.
A planner that raises gives a failed row (message in results.csv, "[n failed]" in Table I).

Per object (``objects.csv``): grid, resolution, GPIS fit time, the spread of the centre of mass
over ``com_samples`` joint shape samples (condition 1 of the P_F approximation, RMS and 95th
percentile of the distance to the mean shape's COM, in cells) and the IoU of the mean shape with
the true shape on the planning grid.

**Seeding (common random numbers).** The planner seed of a run is a deterministic function of
(``seed``, object) only, so within one seed every method draws from the same streams: GP-M, GP-P
and GP-P adaptive choose among the *same* 1000 heuristic candidates, GP-G and its re-ranked
variant start from the same initial grasps, and every method's P_F is estimated on the *same*
evaluation samples (what :mod:`~gpis_grasp_ros.core.planners` intends: "methods are comparable").
The simulated executions likewise use one perturbation stream per (seed, object), so all
methods face the same positioning errors. Seeds are derived with
``np.random.SeedSequence`` from CRC-32 hashes of the names — no process-dependent state — so a
parallel run gives exactly the numbers of a serial run (times excepted).

**Parallelism.** Objects are the unit of work: a ``ProcessPoolExecutor`` with the ``spawn``
context runs one object per worker (``--workers``, default ``os.cpu_count()``), each with
BLAS/OpenMP pools limited to one thread with threadpoolctl. The serial path (``--workers 1``)
also limits BLAS to one thread, so results are bit-identical. Workers report finished
(object, method) pairs through a queue; the parent shows a tqdm progress bar (elapsed, rate,
time left) on stderr.

**Outputs** (``--out``): ``table1.md`` (Table I layout with the paper's values in parentheses, plus
Q_N, simulated success, Q_F on the mean, extra rows), ``results.csv``, ``objects.csv``,
``summary.json``, ``pf_bars.png`` (P_F per object and method), ``runtime.png`` (worst-case
planning time, log scale), ``fig4.png`` (objects A-D × GP-M/GP-P/GP-G on GPIS-Blur, as the
paper's Fig. 4), ``objects/<object>.png`` (every method's grasp on the object's GPIS-Blur; the
green line is the true outline), ``convergence.png`` (GP-G's objective vs SCP iteration per
restart, when the planner records it). All figures are matplotlib (Agg) PNGs.

**Calibration** (``--calibration``, :mod:`~gpis_grasp_ros.tools.benchmark.calibration`):
predicted P̃_F / P_F vs simulated success on the true shape for every planned grasp and 200 GP-P
candidates per object; ``calibration.md``, ``calibration.csv``, ``reliability.png`` and
``calibration/reliability_<letter>.png``.

**Fig. 5** (``--fig5``, :mod:`~gpis_grasp_ros.tools.benchmark.fig5`): object D under four
patterns of shape uncertainty, bags written to ``<out>/fig5/bags``; ``fig5/fig5.md``,
``fig5/fig5.png``, ``fig5/results.csv``.

**Scaling run** (``--scaling``): on one object and grid sides M (``SensingParams(grid_size=M)``),
times of segmentation, GPIS fit (:func:`~gpis_grasp_ros.core.pipeline.posterior_from_grids`), drawing
S joint shape samples, GP-G (N_g = 20) and GP-P (brute force and adaptive, K × S as given by
``--grasp-samples`` / ``--shape-samples``; defaults 1000 × 1000). Each time is the shortest of
``--repeats`` runs (other processes on the machine only ever add time). Exponents k of
t = c M^k come from least squares on log t vs log M (:func:`fit_power_law`); the 70-vs-25 growth
is compared, as ratios, with the growth of the original (Matlab/CVX) implementation as given in
the authors' code repository (not in the paper, which defers to its supplementary file). Writes
``scaling.md``, ``scaling.csv`` and ``scaling.png`` into ``--out``.
"""


from gpis_grasp_ros.tools.benchmark.cli import main, parse_args, write_outputs  # noqa: F401
