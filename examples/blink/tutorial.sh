# The commands of docs/tutorial.md, in its order (tests/test_tutorial.py runs them, each on a mesh
# of its own). Each "terminal" region runs until Ctrl-C: give it a terminal of its own.

# tutorial: begin setup
cd examples
export PYTHONPATH=$PWD
# tutorial: end setup

# tutorial: begin validate
cmion-mesh validate blink/lamp
# tutorial: end validate

# tutorial: begin terminal-lamp
cmion-mesh up blink/lamp
# tutorial: end terminal-lamp

# tutorial: begin act-lamp
cmion-mesh act lamp Blink 2
cmion-mesh bb get lamp light/last
# tutorial: end act-lamp

# tutorial: begin act-fails
cmion-mesh act lamp Blink 99
# tutorial: end act-fails

# tutorial: begin terminal-desk
cmion-mesh up blink/desk --remote-type Light
# tutorial: end terminal-desk

# tutorial: begin terminal-competency
cmion-mesh serve-competency blink.competency:Blink --embodiment desk
# tutorial: end terminal-competency

# tutorial: begin act-desk
cmion-mesh act desk Blink 5
# tutorial: end act-desk

# tutorial: begin mind-clash
cmion-mesh serve-mind blink.mind:Keeper --embodiment desk
# tutorial: end mind-clash

# tutorial: begin terminal-mind
cmion-mesh serve-mind blink.mind:Keeper --embodiment desk --name watcher --parameters 4
# tutorial: end terminal-mind

# tutorial: begin watch
cmion-mesh bb get desk light/last
# tutorial: end watch

# tutorial: begin migrate
cmion-mesh migrate blinky --to desk
cmion-mesh bb get desk light/last
# tutorial: end migrate

# tutorial: begin migrate-back
cmion-mesh migrate blinky --to lamp
cmion-mesh bb get lamp light/last
# tutorial: end migrate-back

# tutorial: begin terminal-launch
cmion-mesh launch blink/blink.launch.toml
# tutorial: end terminal-launch
