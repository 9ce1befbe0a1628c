"""P^{r,in} = -sum_j P_j^{r,out}: each neighbour's power carried to the sample's time along its rate, bounded."""

from __future__ import annotations

import pytest

from service.core.interaction import incoming_reference, outgoing_power_at


def test_in_lockstep_the_reference_is_the_negated_sum():
    assert incoming_reference(0.5, [(0.5, 800.0, 10.0), (0.5, 400.0, -5.0)], 0.01, 0.002) == (-1200.0, -5.0)


def test_a_message_is_carried_along_its_rate_by_at_most_the_horizon_either_way():
    # 1 ms old at +1 kW/s: +1 W; 5 ms old: only the 2 ms horizon, +2 W; 1 ms in the future (late sample): -1 W
    assert outgoing_power_at(0.101, 0.100, 500.0, 1000.0, 0.01, 0.002) == pytest.approx(501.0)
    assert outgoing_power_at(0.105, 0.100, 500.0, 1000.0, 0.01, 0.002) == pytest.approx(502.0)
    assert outgoing_power_at(0.099, 0.100, 500.0, 1000.0, 0.01, 0.002) == pytest.approx(499.0)


def test_a_message_on_another_clock_is_taken_as_it_is():
    """|t - t_j| beyond stale_s: the two clocks are not comparable, so no extrapolation."""
    assert outgoing_power_at(5.0, 0.1, 500.0, 1000.0, 0.01, 0.002) == 500.0
