"""rclpy wrappers of the estimator cores, one executable per node.

``PIPELINE`` lists the nodes in data-flow order; the launcher starts them in this order and,
for deterministic replay, gives node *i* a release delay of *i* replay ticks (see
``ros.runtime``).
"""

from dataclasses import dataclass


@dataclass(frozen=True)
class NodeSpec:
    name: str          # ROS node name
    module: str        # python -m module runs it
    executable: str    # console script installed under lib/vehicle_estimation
    depth: int         # position in the data flow (fusion 0 ... mass 3)
    node_class: str    # the rclpy Node subclass in ``module`` (``replay --in-process`` builds it)


# Paper 004 Fig. 1: the slope observer needs the state's vx and vy (fast signals: a lag of
# even 0.1 s shows as degrees of slope at every brake onset), while the state filter only
# needs the slope and the mass, which change slowly. So the state runs before the slope, and
# state <- slope, state <- mass are the feedback edges (looked up with sync.feedback_lag).
PIPELINE = (
    NodeSpec("fusion", "vehicle_estimation.ros.fusion_node", "fusion_node", 0, "FusionNode"),
    NodeSpec("vehicle_state", "vehicle_estimation.ros.state_node", "state_node", 1, "StateNode"),
    NodeSpec("road_slope", "vehicle_estimation.ros.slope_node", "slope_node", 2, "SlopeNode"),
    NodeSpec("mass", "vehicle_estimation.ros.mass_node", "mass_node", 3, "MassNode"),
)
