"""The robot descriptions ship inside the wheel and are found from it; the CLI runs as a module."""

import subprocess
import sys
import zipfile


from robotdemo.assets import ROBOT_URDF, urdf_root


def test_urdf_root_in_checkout_is_top_level_folder():
    assert urdf_root().name == "urdf" and (urdf_root() / ROBOT_URDF).is_file()


def test_wheel_carries_descriptions_and_data(tmp_path):
    """Build the wheel (no network: the hatchling build backend is already installed with the project's
    build requirements) and check the URDFs and the material catalogue are inside."""
    result = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                             "-w", str(tmp_path), str(urdf_root().parent)], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-2000:]
    wheel = next(tmp_path.glob("robotdemo-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    assert f"robotdemo/_urdf/{ROBOT_URDF}" in names
    assert "robotdemo/_urdf/scene/table.urdf" in names
    assert "perception/materials.toml" in names
    assert "controllers/ik.py" in names
    assert "robotdemo/checkpoints/touchformer_fire/model.safetensors" in names


def test_python_dash_m_shows_help():
    result = subprocess.run([sys.executable, "-m", "robotdemo", "--help"], capture_output=True, text=True)
    assert result.returncode == 0 and "scene" in result.stdout and "bench" in result.stdout
