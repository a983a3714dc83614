"""Pipeline stages: pure functions from one artifact to the next."""
