"""The live view of a run and the replay of a finished one, in the browser.

An observer takes a run's data from Zenoh read-only (:mod:`swarm.live.feed`: the world's
``world/view/*`` payloads, the followers' observations, ``world/done``) or from a run folder
(:func:`swarm.live.store.load_run`) into a :class:`swarm.live.store.RunStore`; a Bokeh server
(:mod:`swarm.live.server`) draws the store on a page (:mod:`swarm.live.page`). Nothing here
imports ``world``: the observer may run on another host (a test enforces it).
"""

DEFAULT_PORT = 5006  # of the page on 127.0.0.1 (Bokeh's usual port)
