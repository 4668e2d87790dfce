"""The reconstruction loop of Fig. 3 as stages over a working set:
points -> mesh -> signs -> values -> test -> subdivide -> relax -> curve."""
