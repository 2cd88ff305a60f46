#!/usr/bin/env bash
# Regenerate the data of the worked example (examples/ur5/README.md): the UR5 model with three
# markers on the tool, and simulated laser-tracker measurements of those markers in the tracker's
# own frame. Run from anywhere; the files are written next to this script (replacing them).
set -euo pipefail
cd "$(dirname "$0")/../.."
ex=examples/ur5

# The model: the URDF chain base_link -> tool0, in mm and rad ...
cdra-jax import urdf "$ex/ur5_robot.urdf" --base base_link --tip tool0 --out "$ex/ur5_markers.toml" --force
# ... plus three reflectors on the tool, positions known only roughly (calibrate = true).
cat >> "$ex/ur5_markers.toml" <<'TOML'

# Three laser-tracker reflectors on the tool flange (mm, tool frame), positions known only to
# a few centimetres: calibrate = true identifies them with the frames.
[[markers]]
name = "m1"
xyz = [0.0, 60.0, 30.0]
calibrate = true

[[markers]]
name = "m2"
xyz = [50.0, -40.0, 30.0]
calibrate = true

[[markers]]
name = "m3"
xyz = [-50.0, -40.0, 30.0]
calibrate = true
TOML

# The tracker: 0.03 mm per point, robot world frame at (300, -250, 100) mm, turned 90 degrees
# about z in the tracker's frame; a fifth of the reflectors hidden per pose; the true reflector
# positions up to 20 mm off the model's.
device=(--device-frame 300 -250 100 0 0 1.5708)
noise=(--noise-pos 0.03)
cdra-jax simulate --model "$ex/ur5_markers.toml" --poses 36 --seed 1 --points --occlusion 0.2 \
    --marker-error 20 "${noise[@]}" "${device[@]}" --out "$ex/fit.csv" --truth "$ex/truth.json" --force
# Held-out poses of the same arm (same frame errors and reflectors: --errors truth.json).
cdra-jax simulate --model "$ex/ur5_markers.toml" --poses 40 --seed 2 --points --occlusion 0.2 \
    --errors "$ex/truth.json" "${noise[@]}" "${device[@]}" --out "$ex/test.csv" --force
