#!/usr/bin/env bash
# Rebuilds spark-three.min.js, the viewer `cubecloud share` embeds in each page, from the npm
# registry at the versions package.json pins (package-lock.json holds their hashes), and copies
# the licences beside it. Needs node and npm; run it from anywhere.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
cp "$here/package.json" "$here/package-lock.json" "$here/entry.js" "$work/"
cd "$work"
npm ci --no-audit --no-fund --ignore-scripts=false >/dev/null
./node_modules/.bin/esbuild entry.js --bundle --minify --format=iife --legal-comments=none \
  --outfile="$here/spark-three.min.js"
cp node_modules/three/LICENSE "$here/LICENSE-three.txt"
cp node_modules/@sparkjsdev/spark/LICENSE "$here/LICENSE-spark.txt"
cp node_modules/fflate/LICENSE "$here/LICENSE-fflate.txt"
node -e 'for (const p of ["three", "@sparkjsdev/spark", "fflate"]) console.log(p, require(`./node_modules/${p}/package.json`).version)' \
  > "$here/versions.txt"
echo "wrote $here/spark-three.min.js ($(wc -c < "$here/spark-three.min.js") bytes)"
