"""Shared test set-up: a missing tool or package fails under CI=true instead of skipping."""

import os

import torch

IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")

torch.set_num_threads(2)
