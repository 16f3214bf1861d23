"""The code MLflow logs as each fold's model (its "models from code"), and runs when the model is loaded."""

from mlflow.models import set_model

from meshseg.pyfunc import FoldPyfunc

set_model(FoldPyfunc())
