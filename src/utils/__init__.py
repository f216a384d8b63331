"""Helpers with no knowledge of registration, Lightning or Hydra: user errors, paths, atomic files, YAML records, the matrix-product yardstick."""
