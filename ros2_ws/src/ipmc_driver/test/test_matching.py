"""MatchGate: a lock-step start waits for DDS matches, not for the graph alone."""

from __future__ import annotations

import pytest

from ipmc_driver.matching import MatchGate


class Pub:
    def __init__(self, matched: int = 0) -> None:
        self.matched = matched

    def get_subscription_count(self) -> int:
        return self.matched


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def gate(graph: dict[str, int], outputs, clock=None, wait_s=5.0):
    warnings: list[str] = []
    g = MatchGate(lambda topic: graph.get(topic, 0), outputs, warn=warnings.append,
                  wait_s=wait_s, clock=clock or Clock())
    return g, warnings


def test_the_graph_seeing_a_subscription_is_not_enough():
    # The CI failure: model_server's subscription was on the graph, not yet matched.
    pub = Pub(matched=2)
    g, warnings = gate({"/ipmc/reference": 3}, [(pub, "/ipmc/reference", 0)])
    assert not g.ready()
    assert g.short() == {"/ipmc/reference": (2, 3)}
    pub.matched = 3
    assert g.ready() and g.open
    assert not warnings


def test_every_publisher_must_match():
    disp, volt = Pub(2), Pub(1)
    g, _ = gate({"/ipmc/displacement": 2, "/ipmc/voltage": 2},
                [(disp, "/ipmc/displacement", 1), (volt, "/ipmc/voltage", 0)])
    assert not g.ready()
    volt.matched = 2
    assert g.ready()


def test_once_open_it_stays_open():
    pub = Pub(1)
    g, _ = gate({"/x": 1}, [(pub, "/x", 0)])
    assert g.ready()
    pub.matched = 0   # a subscriber left: the run goes on
    assert g.ready()


def test_the_required_minimum_is_never_waived():
    clock = Clock()
    pub = Pub(0)
    g, warnings = gate({}, [(pub, "/ipmc/displacement", 2)], clock=clock)
    for t in (0.0, 10.0, 100.0):
        clock.t = t
        assert not g.ready()
    assert not warnings
    pub.matched = 2
    assert g.ready()


def test_an_unmatched_graph_subscription_is_waived_after_wait_s_with_a_warning():
    clock = Clock()
    pub = Pub(1)
    g, warnings = gate({"/ipmc/reference": 2}, [(pub, "/ipmc/reference", 1)], clock=clock,
                       wait_s=5.0)
    assert not g.ready()
    clock.t = 4.9
    assert not g.ready()
    clock.t = 5.1
    assert g.ready()
    assert len(warnings) == 1 and "/ipmc/reference 1 of 2" in warnings[0]


def test_the_wait_counts_from_when_the_minimum_is_met():
    clock = Clock()
    pub = Pub(0)
    g, _ = gate({"/x": 3}, [(pub, "/x", 1)], clock=clock, wait_s=5.0)
    assert not g.ready()
    clock.t = 20.0
    pub.matched = 1          # the required node matched only now
    assert not g.ready()
    clock.t = 24.0
    assert not g.ready()
    clock.t = 25.5
    assert g.ready()


class Sub:
    def __init__(self, matched: int = 0) -> None:
        self.matched = matched

    def get_publisher_count(self) -> int:
        return self.matched


def test_a_required_publisher_holds_the_gate_though_the_graph_lists_none():
    # The make-test failure: the plant's publishers had matched, the graph did not yet list the
    # controller's command publisher, and the plant stepped on as if nobody commanded it.
    disp, cmd = Pub(3), Sub(0)
    g = MatchGate(lambda topic: 3, [(disp, "/ipmc/displacement", 1)],
                  inputs=[(cmd, "/ipmc/command_stamped", 1)],
                  count_publishers=lambda topic: 0, clock=Clock())
    assert not g.ready()
    assert g.short() == {"/ipmc/command_stamped": (0, 1)}
    cmd.matched = 1          # DDS matched it; the graph still lists none
    assert g.ready()


def test_a_publisher_the_graph_lists_is_waited_for_then_waived():
    clock = Clock()
    cmd = Sub(0)
    warnings: list[str] = []
    g = MatchGate(lambda topic: 0, [], inputs=[(cmd, "/ipmc/command", 0)],
                  count_publishers=lambda topic: 1, warn=warnings.append, clock=clock)
    assert not g.ready()
    clock.t = 5.1
    assert g.ready()
    assert len(warnings) == 1 and "/ipmc/command 0 of 1" in warnings[0]


def test_inputs_need_the_graphs_publisher_count_and_one_endpoint_per_topic():
    with pytest.raises(ValueError, match="count_publishers"):
        MatchGate(lambda topic: 0, [], inputs=[(Sub(), "/x", 1)])
    with pytest.raises(ValueError, match="one endpoint per topic"):
        MatchGate(lambda topic: 0, [(Pub(), "/x", 0)], inputs=[(Sub(), "/x", 0)],
                  count_publishers=lambda topic: 0)
