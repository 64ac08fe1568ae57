"""fsjax.evolve: typed pipeline search, a whole GA population evaluated in one compiled call.

* :mod:`.genome` -- stage vocabularies and type skeletons from the registry, genomes, decoding,
  champions stored by op name.
* :mod:`.population` -- :class:`Evaluator`: all genomes of a skeleton over all images of a split
  in one call (``lax.switch`` per stage, ``lax.map`` over individuals), sharded across devices.
* :mod:`.problems` -- synthetic problems with exact truth (denoise, binarize, edges, count) and
  :func:`problem_from_pairs` for user data.
* :mod:`.search` -- the GA, random search at equal budget, knob refinement.
* :mod:`.baselines` -- identity, best single op, hand pipeline.
* :mod:`.runs` -- robust runs over seeds, written to a directory.
"""

from .baselines import Candidate as Candidate
from .baselines import best_single_op as best_single_op
from .genome import DEFAULT_VOCABULARY as DEFAULT_VOCABULARY
from .genome import Skeleton as Skeleton
from .genome import champion_record as champion_record
from .genome import decode as decode
from .genome import encode as encode
from .genome import enumerate_skeletons as enumerate_skeletons
from .genome import stage_vocabulary as stage_vocabulary
from .genome import type_skeleton as type_skeleton
from .population import Evaluator as Evaluator
from .problems import PROBLEMS as PROBLEMS
from .problems import Problem as Problem
from .problems import make_problem as make_problem
from .problems import problem_from_pairs as problem_from_pairs
from .runs import BaselineMissingError as BaselineMissingError
from .runs import RunReport as RunReport
from .runs import run_problem as run_problem
from .runs import write_run as write_run
from .search import GAConfig as GAConfig
from .search import evolve as evolve
from .search import random_search as random_search
from .search import refine as refine


def __getattr__(name):
    if name == "skeleton":  # renamed type_skeleton (fsjax.ops.skeleton is the morphological skeleton)
        from . import genome

        return genome.__getattr__(name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
