# Source this to run cargo by hand: points torch-sys at the project-local PyTorch venv.
#   source scripts/env.sh && cargo build --release
_junction_root="$(cd "$(dirname "${BASH_SOURCE[0]:-$0}")/.." && pwd)"
export VIRTUAL_ENV="$_junction_root/.venv"
export PATH="$VIRTUAL_ENV/bin:$PATH"
export LIBTORCH_USE_PYTORCH=1
unset _junction_root
