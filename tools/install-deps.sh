#!/usr/bin/env bash
# Installs the Debian packages instgs-vk needs to build and run on a fresh machine:
# lavapipe (Mesa's CPU Vulkan), the Vulkan loader and validation layers, Debian's static
# shaderc/glslang/SPIRV-Tools libraries (linked by build.rs through .cargo/config.toml), Xvfb and
# xdotool (the player's window tests). Then Debian's Chromium, for the web-viewer checks of the
# test command (tools/viewers.sh: three.js, Babylon.js, PlayCanvas and CesiumJS drawing our files
# headless): without it those checks are skipped, saying so, so a failed Chromium install is
# reported and does not stop the rest.
set -euo pipefail
installed() { dpkg-query -W -f='${Status}' "$1" 2>/dev/null | grep -q "install ok installed"; }
sudo=""
[ "$(id -u)" -ne 0 ] && sudo="sudo"
updated=0
apt_install() {
    [ $updated = 1 ] || { $sudo apt-get update -qq; updated=1; }
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "$@" > /dev/null
}
pkgs=(mesa-vulkan-drivers libvulkan-dev vulkan-validationlayers libshaderc-dev glslang-dev spirv-tools xvfb xdotool)
missing=()
for p in "${pkgs[@]}"; do
    installed "$p" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
    echo "installing: ${missing[*]}" >&2
    apt_install "${missing[@]}"
fi
if ! installed chromium && [ ! -x "${CHROMIUM:-/usr/bin/chromium}" ]; then
    echo "installing: chromium (the web-viewer checks)" >&2
    apt_install chromium || echo "install-deps: chromium could not be installed: the web-viewer checks will be skipped" >&2
fi
