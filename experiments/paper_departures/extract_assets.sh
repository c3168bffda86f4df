#!/bin/sh
# The original DMCR's sky and floor PNGs (jakegrigsby/dmc_remastered 12fda99, from the fetch-tool
# mirror) into /tmp/dmcr_skies and /tmp/dmcr_floors, for the probes only (never shipped).
G="git --git-dir=/work/.mirror/jakegrigsby+dmc_remastered/repo"
for kind in skies floors; do
  mkdir -p /tmp/dmcr_$kind
  $G ls-tree --name-only HEAD dmc_remastered/assets/$kind/ | while read f; do $G show HEAD:$f > /tmp/dmcr_$kind/$(basename $f); done
done
