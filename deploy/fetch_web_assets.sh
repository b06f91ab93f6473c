#!/usr/bin/env bash
# Rebuild the daemon's vendored web assets from npm (pinned versions; no CDN at run time):
#   capture/daemon/static/vendor/three-viewer.min.js   three.js + OrbitControls + PLYLoader (esbuild)
#   capture/daemon/static/vendor/swagger-ui-bundle.js  Swagger UI for /docs
#   capture/daemon/static/vendor/swagger-ui.css
# The output is byte-for-byte reproducible: same versions, same files (see SHA256SUMS there).
set -euo pipefail
THREE=0.187.0
ESBUILD=0.28.2
SWAGGER=5.35.0
here="$(cd "$(dirname "$0")" && pwd)"
out="$here/../capture/daemon/static/vendor"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
cd "$work"
npm init -y >/dev/null
npm install --no-audit --no-fund --silent "three@$THREE" "esbuild@$ESBUILD" "swagger-ui-dist@$SWAGGER"
cp "$here/web/three-viewer.js" entry.js
mkdir -p "$out"
./node_modules/.bin/esbuild entry.js --bundle --minify --format=esm --legal-comments=eof \
  --log-level=warning --outfile="$out/three-viewer.min.js"
cp node_modules/swagger-ui-dist/swagger-ui-bundle.js node_modules/swagger-ui-dist/swagger-ui.css "$out/"
{
  echo "three@$THREE (MIT), bundled with esbuild@$ESBUILD from deploy/web/three-viewer.js"
  echo "swagger-ui-dist@$SWAGGER (Apache-2.0)"
  echo
  echo "== three.js LICENSE =="; cat node_modules/three/LICENSE
  echo; echo "== swagger-ui LICENSE =="; cat node_modules/swagger-ui-dist/LICENSE
} > "$out/LICENSES.txt"
(cd "$out" && sha256sum three-viewer.min.js swagger-ui-bundle.js swagger-ui.css > SHA256SUMS)
echo "web assets written to $out"
