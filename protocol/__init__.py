"""The wire: Zenoh keys, typed messages with a validating msgpack codec, session config."""
