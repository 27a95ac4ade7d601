"""Recordings and exports of presses: MCAP (live and export), rosbag2, LeRobot."""
