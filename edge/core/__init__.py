"""Pure code shared by the robot and training: configuration, errors, preprocessing,
recordings, the encoder and database, prompts, images and the VLM client. Imports nothing
from the daemon, the drivers, the simulator or the tools."""
