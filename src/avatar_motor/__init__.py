"""avatar-motor: a real-time generative motor system for interactive 3D avatars."""
__version__ = "0.1.0"
