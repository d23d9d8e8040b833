#!/usr/bin/env bash
# Fetch the two public SensoDrive SENSO-Wheel clients at the exact commits the outside check
# used, into a clients folder that is git-ignored (their code is never committed here), and
# install NumPy 1.x into a side folder for the lflipse client (written for NumPy 1.x).
#
# usage: tools/sensodrive_clients/fetch.sh [--no-numpy] [DIR]
#   DIR  default $STEERLAB_SENSODRIVE_CLIENTS, else <repo>/sensodrive-clients
# env:  JOAN_URL, LFLIPSE_URL  clone from elsewhere (a mirror, a local copy)
#       PYTHON                 the Python NumPy is installed for (default <repo>/.venv/bin/python)
#
# Layout made (what the run_*.py scripts read):
#   DIR/repos/joan, DIR/repos/gt-state-feedback-observer   blobless clones (no work tree)
#   DIR/joan/joansensodrive.py, hardwaremanager_inputtypes.py             tud-hri/joan master 789efcf
#   DIR/joan/joansensodrive_develop.py, hardwaremanager_inputtypes_develop.py   branch develop cd76726
#   DIR/lflipse/SensoDriveMultiprocessing.py, Lowpassfilter_Biquad.py     lflipse 3157ab0
#   DIR/lflipse/SensoDriveTest_LT.py       Experiment/SensoDrive/SensoDriveTest.py at 06daaad (= 99c4424^)
#   DIR/np1/                               numpy==1.26.4 (the newest numpy<2), pip --target
# Each file is `git show COMMIT:PATH`, byte-for-byte, then checked against clients.sha256.
set -euo pipefail

here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
repo=$(cd "$here/../.." && pwd)
numpy=1
if [[ "${1:-}" == "--no-numpy" ]]; then
  numpy=0
  shift
fi
dir=${1:-${STEERLAB_SENSODRIVE_CLIENTS:-$repo/sensodrive-clients}}
joan_url=${JOAN_URL:-https://github.com/tud-hri/joan.git}
lflipse_url=${LFLIPSE_URL:-https://github.com/lflipse/gt-state-feedback-observer.git}
python=${PYTHON:-$repo/.venv/bin/python}
[[ -x "$python" ]] || python=python3

JOAN_MASTER=789efcf34fbdecb8d32228569d8402f69815e32d   # master, 2023-01-31
JOAN_DEVELOP=cd76726b5552e65f7a8863e7397be6bc4e8204e1  # develop, 2023-11-15
LFL_MASTER=3157ab0f0f157b8cab4ab2b2e0650c55149896e7    # master
LFL_LT=06daaad8d9d19951112e31ab2779a4eeefcfe7ee        # 99c4424^, 2021-05-18

mkdir -p "$dir/repos" "$dir/joan" "$dir/lflipse"
dir=$(cd "$dir" && pwd)

# clone URL NAME COMMIT... : a blobless clone (commits and trees; file contents on demand),
# then make sure every COMMIT is there (fetched by id if no branch reaches it any more).
clone() {
  local url=$1 name=$2 sha
  shift 2
  if [[ ! -d "$dir/repos/$name" ]]; then
    git clone --quiet --filter=blob:none --no-checkout "$url" "$dir/repos/$name"
  fi
  for sha in "$@"; do
    git -C "$dir/repos/$name" cat-file -e "$sha^{commit}" 2>/dev/null ||
      git -C "$dir/repos/$name" fetch --quiet --filter=blob:none origin "$sha"
  done
}

# take NAME COMMIT PATH DEST : the file as committed
take() {
  git -C "$dir/repos/$1" show "$2:$3" >"$dir/$4.part"
  mv "$dir/$4.part" "$dir/$4"
  echo "  $4  <-  $1 ${2:0:7}:$3"
}

echo "clients folder: $dir"
clone "$joan_url" joan "$JOAN_MASTER" "$JOAN_DEVELOP"
clone "$lflipse_url" gt-state-feedback-observer "$LFL_MASTER" "$LFL_LT"

hm=modules/hardwaremanager
take joan "$JOAN_MASTER" $hm/hardwaremanager_inputs/joansensodrive.py joan/joansensodrive.py
take joan "$JOAN_MASTER" $hm/hardwaremanager_inputtypes.py joan/hardwaremanager_inputtypes.py
take joan "$JOAN_DEVELOP" $hm/hardwaremanager_inputs/joansensodrive.py joan/joansensodrive_develop.py
take joan "$JOAN_DEVELOP" $hm/hardwaremanager_inputtypes.py joan/hardwaremanager_inputtypes_develop.py
sd=Controller_Design/SensoDrive
take gt-state-feedback-observer "$LFL_MASTER" $sd/SensoDriveMultiprocessing.py lflipse/SensoDriveMultiprocessing.py
take gt-state-feedback-observer "$LFL_MASTER" $sd/Lowpassfilter_Biquad.py lflipse/Lowpassfilter_Biquad.py
take gt-state-feedback-observer "$LFL_LT" Experiment/SensoDrive/SensoDriveTest.py lflipse/SensoDriveTest_LT.py
if ! (cd "$dir" && sha256sum --quiet -c "$here/clients.sha256"); then
  echo "checksum mismatch against $here/clients.sha256" >&2
  exit 1
fi
echo "  checksums: ok"

if [[ $numpy == 1 ]]; then
  if compgen -G "$dir/np1/numpy-1.*.dist-info" >/dev/null; then
    echo "NumPy 1.x already in $dir/np1"
  else
    echo "installing numpy==1.26.4 into $dir/np1 (for $python)"
    "$python" -m pip install --quiet --no-warn-conflicts --target "$dir/np1" "numpy==1.26.4"
  fi
fi
echo "done. Run, e.g.: $python $here/run_lflipse.py --clients $dir"
