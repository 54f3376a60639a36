from .cli import app

app(prog_name="python -m sghr_gtsam")
