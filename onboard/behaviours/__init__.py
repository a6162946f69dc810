"""Shipped behaviours. Importing this package imports (and so registers) every module in it: a new
behaviour dropped into this folder is available by name without editing anything else."""
import importlib
import pkgutil

for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")
