#!/usr/bin/env bash
# The processor this machine runs on, as the run scripts record it beside each attempt (machines change
# between sessions, and a run's seconds and arithmetic are those of its processor): cpu family, model
# and model name of the first processor in /proc/cpuinfo, e.g. "family 25 model 17 AMD EPYC";
# "unknown" where /proc/cpuinfo names no family, model and model name.
awk -F'\t*: ' '$1 == "cpu family" {f = $2} $1 == "model" {m = $2} $1 == "model name" && f != "" && m != "" {print "family " f " model " m " " $2; found = 1; exit}
  END {if (!found) print "unknown"}' /proc/cpuinfo 2> /dev/null || echo unknown
