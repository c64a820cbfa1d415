"""Hold a lock-step start until the subscriptions the graph shows have matched the publishers.

The ROS graph (``count_subscribers``) can list a subscription before DDS has matched it with a
publisher, and a volatile subscription gets nothing published before its match. In a lock-step
run the first samples go out in a burst on the first ``/clock``: a subscription that matched
a few milliseconds late lost them. Seen in CI: ``model_server`` missed the first three
references, never answered them, and the controller waited 5 s for their feedforward.

The same holds the other way: the graph can lag DDS, so a plant whose publishers have matched
the controller's subscriptions may not yet list the controller's command publisher, and took
that for "nobody commands me" and stepped on (seen once in ``make test``). So a gate can also
wait for its subscriptions' matched publishers (``inputs``).

No rclpy import: a gate takes the node's ``count_subscribers`` / ``count_publishers`` and each
publisher's ``get_subscription_count`` / subscription's ``get_publisher_count`` (the matched
endpoints), so it is tested with stand-ins.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Protocol

# Longest wall-time hold for subscriptions the graph shows that have not matched, s: one that
# never matches (QoS incompatible, e.g. a transient-local echo of a volatile topic) must not
# stop the run.
MATCH_WAIT_S = 5.0


class _Publisher(Protocol):
    def get_subscription_count(self) -> int: ...


class _Subscription(Protocol):
    def get_publisher_count(self) -> int: ...


class MatchGate:
    """``ready()`` is True once every endpoint has matched its topic's peers.

    ``outputs``: (publisher, topic, at_least) triples. A publisher must match at least
    ``at_least`` subscriptions (no time limit: the nodes the run needs) and every subscription
    the graph shows on its topic (for at most ``wait_s`` of wall time once every minimum is met;
    then ``warn`` is called once with the topics still short, and the gate opens).
    ``inputs``: (subscription, topic, at_least) triples, the same with publishers (the graph's
    from ``count_publishers``, required with ``inputs``).
    """

    def __init__(self, count_subscribers: Callable[[str], int],
                 outputs: Sequence[tuple[_Publisher, str, int]], *,
                 inputs: Sequence[tuple[_Subscription, str, int]] = (),
                 count_publishers: Callable[[str], int] | None = None,
                 warn: Callable[[str], None] = print, wait_s: float = MATCH_WAIT_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if inputs and count_publishers is None:
            raise ValueError("a gate on inputs needs count_publishers")
        # (matched count, graph count, topic, at_least) for every endpoint.
        self._ends = [(pub.get_subscription_count, count_subscribers, topic, at_least)
                      for pub, topic, at_least in outputs]
        self._ends += [(sub.get_publisher_count, count_publishers, topic, at_least)
                       for sub, topic, at_least in inputs]
        topics = [topic for *_, topic, _ in self._ends]
        if len(set(topics)) != len(topics):
            raise ValueError(f"one endpoint per topic, got {topics}")
        self._at_least = {topic: at_least for *_, topic, at_least in self._ends}
        self._warn = warn
        self.wait_s = wait_s
        self._clock = clock
        self._since: float | None = None
        self.open = False

    def short(self) -> dict[str, tuple[int, int]]:
        """Topic -> (matched, needed) for every publisher still short."""
        out = {}
        for matched_count, graph_count, topic, at_least in self._ends:
            matched = matched_count()
            needed = max(at_least, graph_count(topic))
            if matched < needed:
                out[topic] = (matched, needed)
        return out

    def ready(self) -> bool:
        if self.open:
            return True
        short = self.short()
        if not short:
            self.open = True
            return True
        # The required minimum is never waived, and the graph's extra subscriptions get
        # wait_s from the moment it is met.
        if any(m < self._at_least[t] for t, (m, _) in short.items()):
            self._since = None
            return False
        now = self._clock()
        if self._since is None:
            self._since = now
        if now - self._since < self.wait_s:
            return False
        self._warn("starting with endpoint(s) the graph shows but DDS has not matched "
                   f"after {self.wait_s:g} s (QoS incompatible?): "
                   + ", ".join(f"{t} {m} of {n}" for t, (m, n) in short.items()))
        self.open = True
        return True
