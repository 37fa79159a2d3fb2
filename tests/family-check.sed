# `make models-check`: the commands of `make models` (from `make -n`) with budgets of a few steps
# and evaluations of one or two rollouts, so that the whole recipe runs in minutes
/ (limits|train|distill|adapt|ship|eval) /!d
s#(limits --config \S+)#\1 --set anchors=16 --set pool=400 --set held_out=400#
s#(train --config \S+)#\1 --set steps=3 --set stop_at=0 --set checkpoint_every=2 --set batch=8#
s#(distill --config \S+)#\1 --set steps=3 --set batch=4#
s#(adapt --config \S+)#\1 --set steps=3 --set max_minutes=0 --set checkpoint_every=2#
s#(eval realism [^>]*)#\1 --n 2 --seconds 2 --stability-seconds 2 #
s#(eval impulses [^>]*)#\1 --n 2 --seconds 1 #
s#(eval samplers [^>]*)#\1 --n 2 --control-n 2 --max-avatars 2 #
s#(eval (actions|persona) [^>]*)#\1 --n 1 --seconds 1 --encoder-steps 5 #
s#(eval reach [^>]*)#\1 --n 1 --seconds 1 #
