"""Test peers of the service: an instrumented fake vehicle link, controllable cameras, an in-process
service harness. (The MAVLink autopilot peer is tests/mavlink_peer.py.)"""
