"""The services of ``vt-edge run``: lifecycle, sensor path, press, recognition, compute
process, API and events, episode store, metrics, systemd."""
