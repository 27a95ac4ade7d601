"""How people and machines reach the runtime: the HTTP API and operator page, MQTT."""
