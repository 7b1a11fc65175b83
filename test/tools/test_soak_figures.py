"""The soak's parameter-latency figures: calls a restarted node could not answer are counted apart."""

from gpis_grasp_ros.tools.soak_load import PING_WAIT_S, latency_table, split_by_restarts


def test_unanswered_calls_split_by_the_restart_windows_of_their_node():
    stop, up = 1000.0, 1003.0
    sent = {'planner_node': [stop - PING_WAIT_S - 0.01, stop - 1.0, stop + 2.0, up + 0.01, 2000.0],
            'gpis_node': [stop + 1.0]}
    table = latency_table({'planner_node': [0.01] * 10, 'gpis_node': [0.02] * 5}, sent)
    out = split_by_restarts(table, [('planner_node', stop, up)])
    # sent within the wait before the stop, or while the node was down: the restart's; the rest count
    assert out['planner_node']['unanswered_during_restart'] == 2
    assert out['planner_node']['unanswered'] == 3
    # another node's restart windows do not excuse this node
    assert out['gpis_node']['unanswered_during_restart'] == 0
    assert out['gpis_node']['unanswered'] == 1
    assert 'unanswered_sent_at' not in out['planner_node']
    assert out['planner_node']['calls'] == 10


def test_no_restarts_leaves_every_unanswered_call_counted():
    out = split_by_restarts(latency_table({'a': [0.1]}, {'a': [1.0, 2.0]}), [])
    assert out['a']['unanswered'] == 2 and out['a']['unanswered_during_restart'] == 0


def test_slope_and_its_error_recover_a_known_drift_under_a_sawtooth():
    import numpy as np

    from gpis_grasp_ros.tools.soak_load import slope_with_error_per_1000
    x = np.arange(0, 4000, 10.0)
    saw = 20.0 * ((x % 130) / 130 - 0.5)  # +-10 MB sawtooth, not a multiple of the block length
    for drift in (0.0, 5.0):  # MB per 1000
        slope, se = slope_with_error_per_1000(list(x), list(400 + drift * x / 1000 + saw))
        assert abs(slope - drift) < 3 * se + 0.2
        assert se < 1.0
    # a drift of 5 MB per 1000 is told apart from none
    slope, se = slope_with_error_per_1000(list(x), list(400 + 5.0 * x / 1000 + saw))
    assert slope - 3 * se > 0
