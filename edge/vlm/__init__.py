"""The VLM side of recognition: the OpenAI-compatible client (:mod:`.client`), the prompt
templates (:mod:`.prompt`) and the images sent with them (:mod:`.images`). Imports only the
core; the daemon, the tools and training use it."""
