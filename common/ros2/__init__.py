"""ROS 2 over Zenoh without a ROS install: key layouts, graph (liveliness) tokens, CDR.

Shared by the edge's live ``ros2`` frame source and the mapper's ROS 2 output; pure
functions plus a thin wrapper over ``rosbags``' typestore (a maintained CDR library).

Two key layouts (``layout``):

* ``rmw_zenoh`` (ROS 2's Zenoh middleware): data key
  ``<domain>/<topic without leading slash>/<dds type>/<type hash>``, e.g.
  ``0/camera/color/image_raw/sensor_msgs::msg::dds_::Image_/RIHS01_<64 hex>``. The type
  hash is ``RIHS01_...`` on Jazzy and later, ``TypeHashNotSupported`` on Humble; we accept
  any hash on input (subscribe with ``*`` for type and hash). Each node / publisher /
  subscription also holds a liveliness token
  ``@ros2_lv/<domain>/<zid>/<nid>/<id>/<NN|MP|MS|SS|SC>/<enclave>/<namespace>/<node>
  [/<topic>/<type>/<hash>/<qos>]`` with every ``/`` inside a component written ``%``
  (``%`` alone = empty / root). That is what ``ros2 topic list`` reads.
* ``bridge`` (zenoh-bridge-ros2dds): data key = the topic without its leading slash,
  no type in the key (the reader infers it, see :func:`common.ros2.cdr.deserialize_any`).

Payloads are the same in both: CDR with the 4-byte encapsulation header (``00 01 00 00``
little endian). rmw_zenoh publishers attach ``(int64 sequence number, int64 source
timestamp ns, 16-byte gid)`` in Zenoh's serialization format (:func:`cdr.attachment`).
"""
