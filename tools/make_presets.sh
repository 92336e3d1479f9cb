#!/usr/bin/env bash
# Regenerates the preset media in data/media/<name>/: builds each with
# `svkernel medium build` (the standard build: profiles under collimated and
# diffuse light, both bases, planned kernel tallies, the meta-model, checks
# against fresh simulations) into out/media/<name>/ (resumable: run it
# again after an interruption), then copies the models, the manifest with
# its accuracy, and an accuracy table into data/media/<name>/.
#
#   bash tools/make_presets.sh        # about 4–5 min per medium on 2 cores
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release --quiet
mkdir -p out/media
while read -r name eta g; do
  work="out/media/$name"
  ./target/release/svkernel medium build --eta "$eta" --g "$g" --out "$work" | tee "$work.txt"
  mkdir -p "data/media/$name"
  cp "$work"/{basis.json,basis_diffuse.json,metamodel.json,medium.json} "data/media/$name/"
  {
    printf '# Preset `%s`: η = %s, g = %s\n\n' "$name" "$eta" "$g"
    printf 'Built by `svkernel medium build --eta %s --g %s` on 2 cores.\n\n' "$eta" "$g"
    tail -n +2 "$work.txt"
  } > "data/media/$name/accuracy.md"
done <<'LIST'
skin 1.4 0.8
index-matched 1.0 0.0
LIST
