# h39o: perf script output -> self samples by leaf function under each root symbol (perf script -i X.data > X.script; python3 h39o_perf_collapse.py X.script "Index::remove" ...)
import collections, sys
# usage: collapse.py SCRIPT ROOTSYM...: self samples under each root symbol (leaf function)
stacks=open(sys.argv[1]).read().split('\n\n')
for root in sys.argv[2:]:
    c=collections.Counter(); tot=0
    for st in stacks:
        lines=[l.strip() for l in st.strip().split('\n')[1:]]
        syms=[l.split(' ',1)[1].rsplit(' (',1)[0].split('+0x')[0] if ' ' in l else l for l in lines]
        if any(root in s for s in syms):
            tot+=1; c[syms[0][:90]]+=1
    print(f'## under {root}: {tot} samples')
    for k,v in c.most_common(6): print(f'  {v:6d} {100*v/max(tot,1):5.1f} %  {k}')
