#!/usr/bin/env bash
# Regenerate the zenoh configs in this folder from the dynqos configs they mirror (tests check they
# are in sync). Each is what `dynqos config zenoh` prints: usable with the official zenohd (-c FILE).
set -euo pipefail
cd "$(dirname "$0")/../.."
DYNQOS=${DYNQOS:-dynqos}
"$DYNQOS" config zenoh deploy/k8s/base/router.toml --role router >deploy/zenoh/router-dev.json5
"$DYNQOS" config zenoh deploy/k8s/overlays/production/router.toml --role router >deploy/zenoh/router-production.json5
"$DYNQOS" config zenoh deploy/k8s/overlays/production/edge.toml --role edge >deploy/zenoh/edge-production.json5
"$DYNQOS" config zenoh deploy/systemd/onboard.toml --role drone >deploy/zenoh/drone-production.json5
"$DYNQOS" config zenoh deploy/k8s/overlays/production/router.toml --role router >deploy/k8s/overlays/production-zenohd/router.json5
