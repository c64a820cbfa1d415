"""QoS profiles shared by the nodes of several packages (no node code here)."""

from rclpy.qos import QoSDurabilityPolicy, QoSHistoryPolicy, QoSProfile, QoSReliabilityPolicy

# Every /ipmc/* sample matters to recorders, model fitting and the residual (which pairs samples
# by stamp): reliable, deep enough for lock-step bursts (docs/interfaces.md).
SAMPLE_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=100,
                        reliability=QoSReliabilityPolicy.RELIABLE,
                        durability=QoSDurabilityPolicy.VOLATILE)
# A command's subscribers that act on it (driver, plant) keep the last 10: only the latest
# matters to an actuator.
COMMAND_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=10,
                         reliability=QoSReliabilityPolicy.RELIABLE)
# A command's publishers keep 100 (1 s at 100 Hz) in their history: a reliable keep-last writer
# drops the oldest unacknowledged sample once its history is full, so a reader whose
# acknowledgements lag by more than the history (a process starved of CPU) would lose commands.
COMMAND_WRITER_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=100,
                                reliability=QoSReliabilityPolicy.RELIABLE)
DIAGNOSTICS_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=10,
                             reliability=QoSReliabilityPolicy.RELIABLE)

# A lock-step sim_plant's /clock: reliable and transient local, depth 1 (the time is state). A
# node that matches the plant after its first sample still gets t = 0: the reference node
# ticks on it, and a lock-step start waits on that tick. rclpy's own best-effort, volatile
# /clock subscription matches it as before.
LATCHED_CLOCK_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=1,
                               reliability=QoSReliabilityPolicy.RELIABLE,
                               durability=QoSDurabilityPolicy.TRANSIENT_LOCAL)

# Sample topics a lock-step loop pairs by stamp and waits for (/ipmc/reference,
# /ipmc/feedforward): reliable, depth 100 as every sample topic (docs/interfaces.md), and
# transient local, so that a subscriber that matches late (discovery under load) still gets
# the first samples. Volatile subscribers (a recorder, ros2 topic echo) match as before.
PAIRED_SAMPLE_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=100,
                               reliability=QoSReliabilityPolicy.RELIABLE,
                               durability=QoSDurabilityPolicy.TRANSIENT_LOCAL)
