"""``python -m vrnet_ext.cli`` (and ``torchrun -m vrnet_ext.cli train ...``): the ``vrnet`` command."""
from vrnet_ext.cli import run

run()
