"""Configuration of a frame source (one dataclass for every kind, flat keys).

Keys that only one kind reads say so in their help text. Units: metres, seconds, degrees.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from common.config import field_

SourceKind = Literal["synthetic", "replica", "scannet", "tartanair", "recording", "rosbag", "ros2", "sim_camera",
                     "pybullet"]


@dataclass
class SourceConfig:
    """Where the edge's posed RGB-D frames come from and how they are resampled."""

    kind: SourceKind = field_("synthetic", "frame source: synthetic | replica | scannet | tartanair | recording | "
                                           "rosbag | ros2 (live ROS 2 topics over Zenoh) | sim_camera (the synthetic "
                                           "world rendered at poses a simulator sends over Zenoh) | pybullet (the "
                                           "pybullet world, the same way)")
    path: str = field_("", "dataset root / scene directory / recording directory / bag directory (unused by synthetic)")
    robot: str = field_("robot1", "robot id stamped on every frame")
    resolution: str | None = field_(
        None, "output size 'HxW' (e.g. '240x320') or null for native; RGB is resized with area "
              "(shrinking) / bilinear (enlarging) filtering, depth and labels nearest, intrinsics rescaled")
    frame_skip: int = field_(0, "keep frames whose source index i has i % (frame_skip + 1) == 0")
    max_frames: int | None = field_(None, "stop after this many frames (null = all)")
    depth_limit: float | None = field_(
        None, "simulated sensor range in metres: finite depth above it becomes +inf (null = keep; 0 = all +inf)")
    progress: bool = field_(False, "show a tqdm progress bar while iterating")
    fps: float | None = field_(
        None, "frame rate used to stamp frames of sources without time stamps "
              "(null = per-kind default: synthetic 10, replica 30, scannet 30, tartanair 10)")
    world_axes: str = field_(
        "ENU", "axes of the source's world frame (letters E/W, N/S, U/D); poses are re-expressed in ENU "
               "(z up). Read by replica, scannet and rosbag; 'ENU' keeps the source's world as it is")

    # synthetic
    seed: int = field_(0, "synthetic / sim_camera / pybullet: world seed")
    preset: str = field_("default", "synthetic / sim_camera: world preset name")
    trajectory: str = field_("ground", "synthetic: camera trajectory kind, 'ground' or 'drone'")
    hfov: float = field_(90.0, "synthetic / sim_camera / pybullet: horizontal field of view in degrees")
    sky_depth: str = field_("inf", "sim_camera / pybullet: depth of sky pixels, 'inf' (beyond range) or 'nan' "
                                   "(no return)")
    n_frames: int = field_(100, "synthetic: number of trajectory frames")
    trajectory_seed: int | None = field_(
        None, "synthetic: seed of the lap (start point, direction); null = source.seed. Several robots in one "
              "town: the same seed (the world), different trajectory_seed")

    # datasets
    scene: str = field_("", "replica/scannet/tartanair: scene (environment) directory under path "
                            "('' = path is the scene)")
    sequence: str = field_("", "tartanair: trajectory directory, e.g. 'P0000' ('' = path/scene/difficulty is it)")
    difficulty: str = field_("Data_ground", "tartanair: difficulty directory, e.g. 'Data_ground', 'Data_easy', "
                                            "'Data_hard'")
    camera: str = field_("lcam_front", "tartanair: camera name used in the directory and file names")
    depth_cutoff: float = field_(
        100.0, "tartanair: finite depth beyond this (metres) becomes +inf (the reference uses 100, and 50 "
               "for the search-volume benchmark); the sky is ~1e4 m in TartanAir")
    label_map: str = field_(
        "", "scannet: path to scannetv2-labels.combined.tsv to map raw label ids to NYU40 "
            "('' = look for it next to the scene, else keep raw ids)")

    # rosbag and ros2 (same topic, frame, sync and interpolation options)
    rgb_topic: str = field_("", "rosbag/ros2: sensor_msgs/Image or CompressedImage colour topic")
    depth_topic: str = field_("", "rosbag/ros2: depth topic (Image 32FC1 metres / 16UC1 scaled by depth_scale, "
                                  "or compressedDepth)")
    camera_info_topic: str = field_("", "rosbag/ros2: sensor_msgs/CameraInfo topic of the depth camera "
                                        "('' = use 'intrinsics')")
    intrinsics: list[float] | None = field_(
        None, "rosbag/ros2: [fx, fy, cx, cy] at the depth image's native resolution when there is no CameraInfo")
    pose_topic: str = field_("", "rosbag/ros2: geometry_msgs/PoseStamped or nav_msgs/Odometry topic ('' = use /tf)")
    tf_topic: str = field_("/tf", "rosbag/ros2: tf2_msgs/TFMessage topic with dynamic transforms")
    tf_static_topic: str = field_("/tf_static", "rosbag/ros2: tf2_msgs/TFMessage topic with static transforms")
    world_frame: str = field_("", "rosbag/ros2: tf world frame (e.g. 'map', 'odom') when poses come from /tf")
    camera_frame: str = field_(
        "", "rosbag/ros2: tf frame of the depth camera (e.g. 'camera_depth_optical_frame'); with pose_topic, "
            "the static chain from the pose's body frame to it is appended")
    pose_frame: str = field_("", "rosbag/ros2: body frame of pose_topic messages ('' = Odometry child_frame_id)")
    body_axes: str = field_(
        "auto", "rosbag/ros2: axes of the camera body (e.g. FLU, RDF); 'auto' = RDF for '*_optical_frame' "
                "frames, else FLU (REP-103)")
    depth_scale: float = field_(0.001, "rosbag/ros2: metres per unit of integer (16UC1 / mono16) depth")
    sync_tolerance: float = field_(0.05, "rosbag/ros2: max |t_rgb - t_depth| and nearest-pose gap in seconds")
    interpolate_pose: bool = field_(
        True, "rosbag/ros2: interpolate poses (linear translation, slerp rotation) between the samples around a "
              "depth stamp when they are at most pose_max_gap apart; else take the nearest within sync_tolerance")
    pose_max_gap: float = field_(0.5, "rosbag/ros2: the largest gap in seconds between two pose samples to "
                                      "interpolate across")
    use_header_stamps: bool = field_(True, "rosbag/ros2: time stamps from message headers "
                                           "(false = bag / Zenoh receive time)")

    # ros2 (live)
    ros_domain: int = field_(0, "ros2: ROS_DOMAIN_ID of the robot (first chunk of rmw_zenoh keys)")
    ros_keys: Literal["rmw_zenoh", "bridge"] = field_(
        "rmw_zenoh", "ros2: key layout: 'rmw_zenoh' (<domain>/<topic>/<dds type>/<type hash>, any hash) or "
                     "'bridge' (zenoh-bridge-ros2dds: <topic>)")
    ros_connect: list[str] = field_(
        [], "ros2: Zenoh endpoints of the robot's ROS side (e.g. ['tcp/127.0.0.1:7447'] = the local "
            "rmw_zenohd router); [] = the edge's own zenoh section (same network as the base station)")
    ros_queue: int = field_(30, "ros2: bounded buffer per topic (messages); overflow drops the oldest, counted")
    ros_max_delay: float = field_(
        0.5, "ros2: seconds (wall clock) a depth image waits for the colour image and pose samples that bracket "
             "its stamp before it is matched with what has arrived (or skipped and counted)")
    ros_startup_timeout: float = field_(
        0.0, "ros2: give up (error naming the topics seen) if no frame matched within this many seconds; 0 = wait")
    ros_idle_timeout: float = field_(
        0.0, "ros2: end the stream after this many seconds without a new frame; 0 = run until stopped")
    ros_log_every: float = field_(5.0, "ros2: at most one warning line per reason and topic per this many seconds")
