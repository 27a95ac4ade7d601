"""Pure code shared by the robot and training: configuration, errors, preprocessing,
recordings, the encoder and database. Imports nothing from the daemon, the drivers, the VLM
client, the simulator or the tools."""
