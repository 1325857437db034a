import importlib.util
import os
import sys

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

pytest_plugins = ("tests.fixtures",)  # smoke_data, smoke_run: shared by tests/ and probes/; this file imports no entry point


def probe_script(name):
    """A script of probes/ (not a package) imported as a module, e.g. probe_script("ft_pairs")."""
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "probes", f"{name}.py")
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
