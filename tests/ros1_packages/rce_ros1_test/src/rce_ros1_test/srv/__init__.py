# ruff: noqa
from ._Echo import *
