"""mocapskel: template-free skeletons from raw optical motion-capture markers."""
__version__ = "0.1.0"
