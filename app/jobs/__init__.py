"""Build jobs: extracting map image features in the workers and packing a new revision."""
