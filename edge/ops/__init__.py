"""Operating the robot: doctor, calibration, poses, models, retries, exports. They drive the
daemon through its public hooks."""
