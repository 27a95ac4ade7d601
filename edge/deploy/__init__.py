"""Installing the daemon: the systemd unit, udev rules and the install checks."""
