"""inverse: physical-gradient (SIP) and half-inverse-gradient (HIG) training of networks through physics."""

from .hig import HIG, GaussNewton, HIGStepInfo, JacobianMemoryError, hig_update, per_sample_jacobian
from .local_solvers import (
    GradientStepSolver,
    InverseGradientSolver,
    LBFGSBSolver,
    LocalSolver,
    NewtonSolver,
    SolverOperator,
    batch_hessian,
    batch_jacobian,
)
from .nets import MLP, UNet, count_parameters
from .operators import Heat, PhysicsOperator, Poisson, ScaleToy, Sine, SquareToy
from .physgrad import (
    FourierTransform,
    PhysicalGradient,
    QuadraticLoss,
    physgrad,
    physical_gradient_loss,
    physical_update,
)

__all__: list[str] = []
__all__ += [  # operators, local solvers, physical-gradient layer, networks
    "PhysicsOperator", "ScaleToy", "SquareToy", "Sine", "Poisson", "Heat",
    "LocalSolver", "GradientStepSolver", "NewtonSolver", "InverseGradientSolver", "LBFGSBSolver",
    "SolverOperator", "batch_jacobian", "batch_hessian",
    "QuadraticLoss", "FourierTransform", "physical_update", "physical_gradient_loss", "PhysicalGradient",
    "physgrad",
    "UNet", "MLP", "count_parameters",
]
__all__ += ["HIG", "GaussNewton", "HIGStepInfo", "JacobianMemoryError", "hig_update", "per_sample_jacobian"]

from .problems import PROBLEMS, Batch, HeatProblem, Method, PoissonProblem, Problem, SineProblem, get_problem  # noqa: E402
from .train import TrainResult, batch_generator, make_optimizer, train  # noqa: E402

__all__ += [  # problems and the training loop
    "Method", "Batch", "Problem", "SineProblem", "PoissonProblem", "HeatProblem", "PROBLEMS", "get_problem",
    "train", "TrainResult", "batch_generator", "make_optimizer",
]

from .fluid_inverse import FluidMarkerOperator, FluidProblem, frequency_loss  # noqa: E402

__all__ += ["FluidMarkerOperator", "FluidProblem", "frequency_loss"]  # E5 fluid pair and problem

from .pde_inverse import ConvResNet, LinearPartSolver, PDEOperator, PDEProblem, pde_transfer, wiener_gain  # noqa: E402

__all__ += ["PDEOperator", "LinearPartSolver", "ConvResNet", "PDEProblem", "pde_transfer", "wiener_gain"]  # phisim.pde

from .custom import CallableOperator, CustomProblem, load_problem, make_problem  # noqa: E402
from .models import load_model, model_path, predict_file, save_model  # noqa: E402

__all__ += ["CallableOperator", "CustomProblem", "make_problem", "load_problem"]  # your own physics
__all__ += ["load_model", "save_model", "model_path", "predict_file"]  # trained models

from .export import TensorBoardLogger, export_csv  # noqa: E402
from .offline import DatasetSampler, FieldNet, dataset_problem  # noqa: E402

__all__ += ["export_csv", "TensorBoardLogger", "DatasetSampler", "FieldNet", "dataset_problem"]  # offline, CSV
