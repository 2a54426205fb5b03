"""companion: stereo-vision obstacle avoidance for PX4 drones (Haque & Nejadpak, extended)."""

__version__ = "0.1.0"
