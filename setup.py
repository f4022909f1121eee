"""Package metadata for phisim (simulation core) and inverse (physical-gradient training)."""
from setuptools import find_packages, setup

setup(
    name="phisim",
    version="0.1.0",
    description="Differentiable PDE simulation on PyTorch with physical-gradient and half-inverse-gradient training",
    long_description=open("README.md", encoding="utf-8").read(),
    long_description_content_type="text/markdown",
    python_requires=">=3.10",
    packages=find_packages(include=["phisim", "phisim.*", "inverse", "inverse.*"]),
    # the command's parser: standard library only, so `phisim --help` does not import torch
    py_modules=["phisim_cli"],
    install_requires=[
        "numpy>=1.24",
        "scipy>=1.10",
        "pyfftw>=0.13",
        "torch>=2.1",
        "h5py>=3.8",
        "matplotlib>=3.7",
        "tqdm>=4.60",
    ],
    extras_require={
        # the-well: its loader reads our HDF5 files in a test (small pure-Python dependencies)
        # nbclient, nbformat, ipykernel: a test executes the quickstart notebook (inline pictures)
        # pytest-xdist: `bash run.sh test` runs the suite in two worker processes
        "test": ["pytest>=7", "pytest-xdist>=3", "hypothesis>=6", "ruff>=0.4", "the-well", "nbclient>=0.7",
                 "nbformat>=5", "ipykernel>=6"],
        "dev": ["pytest>=7", "pytest-xdist>=3", "hypothesis>=6", "ruff>=0.4", "the-well", "pytest-timeout>=2",
                "nbclient>=0.7", "nbformat>=5", "ipykernel>=6"],
        "well": ["the-well"],
    },
    entry_points={"console_scripts": ["phisim=phisim_cli:main"]},
)
