# disjoint_pool PRESET: sets OTHERS to the generate_scenes arguments of PRESET's disjoint-object training set
# (baselines B and D and V1 train on it): objects the preset's scenes never use, in the preset's own layout and
# depth. Sourced by scripts/benchmark.sh and scripts/confirm_noisy.sh; returns 2 for an unknown preset.
disjoint_pool() {
  case $1 in
    benchmark)  # builtin objects outside generate/presets.py BENCHMARK_POOL
      OTHERS=(--object-pool box_large,box_small,book,cube,can_soup,chips_tube,jar,ball,egg,pill_tube,flowerpot,hex_box,cheese_wedge,pitcher,drill) ;;
    calibrated|cluttered|calibrated-noisy|cluttered-noisy)  # the builtin library without the duck, the one object
      # it shares with the paper library; in the preset's own layout (cluttered: piles) and depth (noisy or exact)
      OTHERS=(--library builtin --object-pool box_large,box_medium,box_small,book,cube,can_soda,can_soup,chips_tube,jar,ball,egg,pill_tube,flowerpot,hex_box,cheese_wedge,lamp,dumbbell,mug,bowl,bottle,pitcher,hammer,banana,drill) ;;
    *) return 2 ;;
  esac
}
