"""Paper 000's learnt pre-estimator: the transformer (and its MLP/LSTM baselines) in
:mod:`.model`, and the features and confidence level it shares with the TA-AEKF and the
training data in :mod:`.features`. Only :mod:`.model` needs torch."""
