"""The topic contract: names (all relative, so namespaces and remapping apply) and joint names.

See the README's "Topic contract" table for types, fields, units, frames and rates.
"""

# Inputs (sensor-data QoS)
IMU = "imu/data"                      # sensor_msgs/Imu, body frame (x fwd, y left, z up)
GNSS = "gnss/fix"                     # sensor_msgs/NavSatFix, WGS84
SPEED = "vehicle/speed"               # geometry_msgs/TwistWithCovarianceStamped, twist.twist.linear.x
JOINT_STATES = "vehicle/joint_states"  # sensor_msgs/JointState, wheels + steering wheel
POWERTRAIN = "vehicle/powertrain"     # sensor_msgs/JointState, engine, load, gear, drive

INPUT_TOPICS = (IMU, GNSS, SPEED, JOINT_STATES, POWERTRAIN)
#: The type of each input (README, "Inputs"): a topic of another type never reaches the nodes.
INPUT_TYPES = {
    IMU: "sensor_msgs/msg/Imu",
    GNSS: "sensor_msgs/msg/NavSatFix",
    SPEED: "geometry_msgs/msg/TwistWithCovarianceStamped",
    JOINT_STATES: "sensor_msgs/msg/JointState",
    POWERTRAIN: "sensor_msgs/msg/JointState",
}

# Outputs (reliable, keep-last)
ODOMETRY = "estimation/odometry"              # nav_msgs/Odometry
IMU_COMPENSATED = "estimation/imu"            # sensor_msgs/Imu, bias-compensated + orientation
IMU_BIAS = "estimation/imu_bias"              # sensor_msgs/Imu: linear_acceleration = accel bias, angular_velocity = gyro bias
ROAD_SLOPE = "estimation/road_slope"          # std_msgs/Float64 [rad], positive uphill
ROAD_SLOPE_STAMPED = "estimation/road_slope_stamped"  # geometry_msgs/Vector3Stamped: x value, y variance, z converged
VEHICLE_STATE = "estimation/vehicle_state"    # geometry_msgs/TwistWithCovarianceStamped
SIDESLIP = "estimation/sideslip"              # std_msgs/Float64 [rad]
SIDESLIP_STAMPED = "estimation/sideslip_stamped"  # geometry_msgs/Vector3Stamped
FUSION_GRADE = "estimation/fusion/road_grade"  # geometry_msgs/Vector3Stamped, pitch-derived grade
SPEED_SCALE = "estimation/speed_scale"        # geometry_msgs/Vector3Stamped: x CAN speed / true speed, y variance, z GNSS-observed
DATUM = "estimation/datum"                    # sensor_msgs/NavSatFix: WGS84 origin of odom once it is ENU (latched)
MASS = "estimation/mass"                      # std_msgs/Float64 [kg]
MASS_STAMPED = "estimation/mass_stamped"      # geometry_msgs/Vector3Stamped: x value, y variance, z converged
DIAGNOSTICS = "/diagnostics"                  # diagnostic_msgs/DiagnosticArray

# Ground truth, in simulated bags
GT_MASS = "ground_truth/mass"                 # std_msgs/Float64 [kg]
GT_ROAD_SLOPE = "ground_truth/road_slope"     # std_msgs/Float64 [rad]
GT_SIDESLIP = "ground_truth/sideslip"         # std_msgs/Float64 [rad]
GT_VEHICLE_STATE = "ground_truth/vehicle_state"  # geometry_msgs/TwistWithCovarianceStamped
GT_ODOMETRY = "ground_truth/odometry"         # nav_msgs/Odometry
GT_DATUM = "ground_truth/datum"               # sensor_msgs/NavSatFix: WGS84 origin of the truth's odometry frame
GT_IMU_BIAS = "ground_truth/imu_bias"         # sensor_msgs/Imu: the IMU's biases, as estimation/imu_bias

GROUND_TRUTH_TOPICS = (GT_MASS, GT_ROAD_SLOPE, GT_SIDESLIP, GT_VEHICLE_STATE, GT_ODOMETRY, GT_DATUM, GT_IMU_BIAS)

# Joint names
WHEEL_JOINTS = ("wheel_fl", "wheel_fr", "wheel_rl", "wheel_rr")
STEERING_JOINT = "steering_wheel"
ENGINE_JOINT = "engine"
ENGINE_LOAD_JOINT = "engine_load"
GEAR_JOINT = "gear"
DRIVE_JOINT = "drive"

# Frames (REP-105)
ODOM_FRAME = "odom"
BASE_FRAME = "base_link"
IMU_FRAME = "imu_link"
GNSS_FRAME = "gnss_link"


def relative(topic: str) -> str:
    """A topic name as the contract writes it: without the leading '/' a bag or a user adds."""
    return topic.strip().lstrip("/")


def parse_remap(text: str) -> tuple[str, str]:
    """``FROM:=TO`` -> ``(FROM, TO)`` as written; ``ValueError`` saying what is malformed."""
    if text.count(":=") != 1:
        raise ValueError(f"remap {text!r} must be FROM:=TO (one ':='), e.g. imu/data:=/sensors/imu")
    source, target = (part.strip() for part in text.split(":="))
    for what, name in (("FROM", source), ("TO", target)):
        if not name.strip("/") or any(c.isspace() for c in name):
            raise ValueError(f"remap {text!r}: in FROM:=TO, {what} must be a topic name without spaces "
                             "(e.g. imu/data:=/sensors/imu)")
    return source, target


def bag_to_contract(remaps, contract_topics) -> dict[str, str]:
    """``{bag topic: contract topic}`` from ``(FROM, TO)`` remap pairs (no leading '/').

    As in ROS (``-r FROM:=TO``), FROM is the name the nodes use and TO the name in the vehicle
    stack or bag: ``imu/data:=/sensors/imu``. The reverse order names the same mapping and is
    taken too, since one side must be a contract topic: ``/sensors/imu:=imu/data``. A pair
    with no contract topic on either side is a ``ValueError`` that says so.
    """
    contract = {relative(t) for t in contract_topics}
    out: dict[str, str] = {}
    for source, target in remaps:
        a, b = relative(source), relative(target)
        if a in contract:
            out[b] = a
        elif b in contract:
            out[a] = b
        else:
            raise ValueError(f"remap {source}:={target}: neither side is a topic of the contract "
                             f"({', '.join(sorted(contract))})")
    return out
