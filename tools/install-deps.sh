#!/usr/bin/env bash
# Installs the Debian packages instgs-vk needs to build and run on a fresh machine:
# lavapipe (Mesa's CPU Vulkan), the Vulkan loader and validation layers, Debian's static
# shaderc/glslang/SPIRV-Tools libraries (linked by build.rs through .cargo/config.toml), Xvfb and
# xdotool (the player's window tests).
set -euo pipefail
pkgs=(mesa-vulkan-drivers libvulkan-dev vulkan-validationlayers libshaderc-dev glslang-dev spirv-tools xvfb xdotool)
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  sudo=""
  [ "$(id -u)" -ne 0 ] && sudo="sudo"
  echo "installing: ${missing[*]}" >&2
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}" >/dev/null
fi
