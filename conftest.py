# Puts the repository root on sys.path so tests import the working copy of torchrl_esrl.
