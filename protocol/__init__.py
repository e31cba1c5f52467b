"""The wire contract of mocap-labeler: message schema, encode/decode and validation, and the static
skeleton description. Imports neither zmq nor jax (a test checks), so any tool can speak it."""
